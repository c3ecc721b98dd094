//! host-sim: independent f64 reference plants for the piezo hysteresis compensator.
//!
//! The plants here are the truth the compensator of `piezo-core` is judged against. They do not call the
//! core's model step: they integrate their own f64 equations with an adaptive Dormand–Prince 5(4) pair
//! ([`ode`]), clip steps at sample instants and input breakpoints, and carry effects no model declares
//! ([`effects`]). Signals ([`signal`]), CSV I/O ([`csv`]), plots ([`plot`]) and the command line ([`cli`])
//! sit on top.

// `!(x > 0.0)` is used on purpose: it rejects NaN as well as out-of-range values.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

pub mod bouc_wen;
pub mod capture;
pub mod cli;
pub mod close_loop;
pub mod compensate;
pub mod csv;
pub mod demo;
pub mod effects;
pub mod identify;
pub mod link;
pub mod ode;
pub mod plant;
pub mod plot;
pub mod reproduce;
pub mod servo_bench;
pub mod signal;
pub mod sim;
pub mod stage_file;
