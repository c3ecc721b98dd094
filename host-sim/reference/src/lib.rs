//! piezo-reference: the independent f64 reference plants that the piezo hysteresis compensator is
//! judged against.
//!
//! The three plants of the source papers — the NAC2024 high-frequency actuator (seed 000), the
//! asymmetric stage (seed 001) and the two-axis flexure stage (seed 002) — written as f64 state-space
//! systems and integrated with an adaptive Dormand–Prince 5(4) pair, with effects that no model
//! declares, the input signals that drive them and the CSV files they write. `host-sim`'s `simulate`
//! and `demo`, the identification tests and the firmware's hardware-in-the-loop tests all take their
//! "measurements" from here.
//!
//! **Why this crate does not depend on `piezo-core`.** The core is the model under test: the
//! firmware, the host simulation and the identification all call its f32 step. A reference that
//! called the same step could not disagree with it, so a test against it could not fail. This crate
//! has its own Bouc-Wen law, its own integrator (variable step in time, not the core's exact
//! increments along the input path; over input holds, exact matrix exponentials in f64),
//! its own mechanics, all in f64; its `Cargo.toml` lists neither
//! `piezo-core` nor `piezo-stage`, so Cargo, not a comment, keeps it independent
//! (`cargo tree -p piezo-reference` shows no `piezo-*` crate). The dependency runs one way only: the
//! tools in `host-sim` use this crate, this crate uses nothing of theirs.
//!
//! # Modules
//!
//! - [`plant`]: the plants behind the [`plant::Plant`] trait — [`plant::Nac2024`] (Bouc-Wen force on
//!   a mass–spring–damper, optional second mode), [`plant::AsymmetricStage`] (Cases I–III, input
//!   time shift and the δ·u·sgn(u̇) term) and [`plant::XyStage`] (two stacks driving a flexure
//!   mechanism, a Lagrange model per axis), and [`plant::BipolarStack`] (a ±90 V stack whose
//!   hysteresis follows the voltage through three dielectric relaxations, with a 740 Hz mode) and
//!   [`plant::RelaxingStack`] (a ±90 V stack whose whole strain relaxes, so its loops widen with
//!   rate, with a stiffening strain and a 740 Hz mode) —
//!   with [`plant::PlantKind`] choosing one by name. Each file states its
//!   equation, parameters and source.
//! - [`bouc_wen`]: the Bouc-Wen law in f64, shared by the plants: its rate ḣ for the ODE and the
//!   jump of h along a held input step ([`bouc_wen::BoucWen::jump`]).
//! - [`ode`]: the adaptive Dormand–Prince 5(4) integrator ([`ode::Dp45`]); every advance lands
//!   exactly on its end time, so callers clip at sample instants and input breakpoints.
//! - [`effects`]: what real data carry and the papers do not declare (creep, drift, sensor delay,
//!   amplifier bandwidth and slew, noise, ADC and DAC quantisation, electrostriction, cross-coupling,
//!   a second mode), each off by default and parsed from `name:key=value,...`.
//! - [`signal`]: input voltages u(t) with u̇(t) and their breakpoints, exact in continuous time
//!   (sine, multisine, chirp, triangle, ramp-edged square, raster, staircase, steps, CSV data), and
//!   the `kind:key=value,...` spec parser.
//! - [`sim`]: [`sim::simulate`] — integrates the joint state (amplifier, plant, creep) between
//!   sample instants and breakpoints, then applies the sensor-side effects; over the holds of
//!   zero-order-hold inputs to a plant that is linear between jumps it propagates exactly instead.
//! - [`hold`]: that exact propagation, x ← x + Ψ(Δ)·ẋ with Ψ(Δ) = ∫₀^Δ e^{As} ds from a
//!   scaling-and-squaring Padé matrix exponential, cached per hold length.
//! - [`csv`]: CSV files of sampled signals with the unit in every column name (`t_s`, `u_V`, `y_m`),
//!   read by the CSV signals and written by simulations.
//!
//! # Adding a plant or an effect
//!
//! A plant is a new file under `src/plant/` implementing [`plant::Plant`] (states, right-hand side,
//! the hysteresis jump at a held input step, outputs, validity checks), a variant of
//! [`plant::PlantKind`] with its name in `from_name` and [`plant::PLANT_NAMES`], and a test in
//! `tests/plants.rs` against the source paper's figures. An effect is a field of
//! [`effects::Effects`], a branch of [`effects::Effects::add_spec`] and a line of
//! [`effects::EFFECT_HELP`]; it acts in [`sim::simulate`] when it is on the signal or sensor side,
//! or through [`effects::Effects::apply_to_plant`] when it changes the plant itself.

// `!(x > 0.0)` is used on purpose: it rejects NaN as well as out-of-range values.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

pub mod bouc_wen;
pub mod csv;
pub mod effects;
pub mod hold;
pub mod ode;
pub mod plant;
pub mod signal;
pub mod sim;
