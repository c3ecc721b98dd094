//! host-sim: the host tools of the piezo hysteresis compensator — identification, close-loop,
//! compensation, figures and the `host-sim` command line — on top of the model under test
//! (`piezo-core`, with the stage file of `piezo-stage`) and the independent reference plants
//! (`piezo-reference`).
//!
//! [`identify`] fits a core model to a record and predicts new data with it; [`close_loop`] reads the
//! residual, names the effect the fit lacks and refits; [`compensate`] computes the voltages the
//! firmware would command; [`demo`], [`reproduce`] and [`servo_bench`] run the core against the
//! reference plants; [`capture`] and [`link`] talk to the firmware (its log, its command link) and
//! turn its frames into records by [`record`]'s one rule;
//! [`identity`] names a stage file's set as the firmware names the set it runs;
//! [`servo_tune`] writes the feedback servo of the stage file; [`learn`] takes one step of iterative
//! learning control and [`learn_bench`] runs it on the XY stage; [`stage_file`] writes the stage file;
//! [`plot`] draws the figures ([`track_plot`] those of a tracking or excitation run); [`cli`] is
//! the command line; [`optimise`] is the one differential
//! evolution, Levenberg–Marquardt and linear solver their fits share; [`uncertainty`] gives a fit's
//! standard errors, correlations and prediction band; [`error`] is the one [`Error`] every command
//! and helper returns, whose text is what the command line prints.
//!
//! The plants, effects, signals, solver and CSV files live in `piezo-reference` (`host-sim/reference`),
//! which does not depend on the core; they are re-exported here ([`plant`], [`sim`], [`signal`],
//! [`effects`], [`ode`], [`bouc_wen`], [`csv`]) so that `host_sim::plant::XyStage` and the like name
//! the same items. The dependency runs one way: these tools use the reference, never the reverse.

// `!(x > 0.0)` is used on purpose: it rejects NaN as well as out-of-range values.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

pub mod capture;
pub mod cli;
pub mod close_loop;
pub mod compensate;
pub mod demo;
pub mod error;
pub mod identify;
pub mod identity;
pub mod learn;
pub mod learn_bench;
pub mod link;
pub mod link_learn;
pub mod link_step;
pub mod optimise;
pub mod plot;
pub mod record;
pub mod reproduce;
pub mod servo_bench;
pub mod servo_tune;
pub mod settle;
pub mod simulate;
pub mod stage_file;
pub mod track_plot;
pub mod uncertainty;

pub use error::{Error, Result};
pub use piezo_reference::{bouc_wen, csv, effects, ode, plant, signal, sim};

/// A typed report as JSON: every report is written through this value, so that its f32 figures
/// are widened to f64 and its keys sorted; a failure is [`Error::Json`].
pub fn to_json(value: &impl serde::Serialize) -> Result<serde_json::Value> {
    serde_json::to_value(value).map_err(Error::from)
}

/// The keys of a JSON object (none for any other value): what a test of a report's shape compares.
#[cfg(test)]
pub(crate) fn json_keys(value: &serde_json::Value) -> std::collections::BTreeSet<&str> {
    value
        .as_object()
        .map(|m| m.keys().map(String::as_str).collect())
        .unwrap_or_default()
}

/// Progress lines of the long commands: to stderr, so that stdout keeps the result.
pub fn progress(line: &str) {
    eprintln!("{line}");
}
