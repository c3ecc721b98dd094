//! `host-sim settle`: the settling time the stage file's model predicts for a step, with the
//! firmware's own controller (piezo-core's compensator, the inverse effect chain, and the servo
//! when asked for) and the firmware's on-target rule (`piezo_core::on_target`).
//!
//! ```text
//! host-sim settle --params STAGE.toml --from A[,B] --to X[,Y] [--tolerance T] [--feedback]
//! ```
//!
//! Per axis (no coupling), from rest at the window's lower end u_min, per tick k as the
//! firmware's loop runs it (`firmware/src/xy_loop.rs`):
//!
//! ```text
//! y[k]        the reading: the stage file's forward model (hysteresis, then its effects: creep,
//!             mode, delay, ...) after the voltage of tick k − 1 (at rest: its output at u_min)
//! w*[k]       the target of r[k] through the inverse effect chain (r[k] itself without effects)
//! u_ff[k]     = compensator(w*[k])   (window and slew limit, a hair inside the guard's)
//! u[k]        = u_ff[k], or servo(r[k−1], y[k], u_ff[k]) with --feedback (feedforward+feedback)
//! on target   |y[k] − r[k−1]| ≤ tolerance for N ticks (the stage file's [x.on_target])
//! ```
//!
//! The reference is A until the axis is on target (at most `--timeout` s), then X: the settling
//! time is the firmware's, the ticks from the first reading that answers X to the first tick of
//! the in-band run that set the flag (`OnTargetState::settle_ticks`), in seconds × T.

use piezo_core::on_target::NOT_SETTLED;
use piezo_core::{
    AxisParams, Compensator, CompensatorState, InverseChain, ModelState, OnTarget, OnTargetState,
    Servo, ServoMode, ServoState,
};
use piezo_stage::{AxisChain, FirmwareSet};
use std::path::PathBuf;

/// Arguments of `settle`.
#[derive(Debug, clap::Args)]
pub struct SettleArgs {
    /// Stage file (TOML), as the firmware runs it.
    #[arg(long)]
    pub params: PathBuf,
    /// Where the stage stands before the step (m): one value for both axes or `X,Y`.
    #[arg(long)]
    pub from: String,
    /// Where the step goes (m): one value for both axes or `X,Y`.
    #[arg(long)]
    pub to: String,
    /// On-target band (m) (default: the stage file's `[x.on_target]`, or its default).
    #[arg(long)]
    pub tolerance: Option<f64>,
    /// Longest time watched for each of the two moves (s).
    #[arg(long, default_value_t = 1.0)]
    pub timeout: f64,
    /// Run the servo too (feedforward+feedback; the file needs `[x.servo]`, `[y.servo]`).
    #[arg(long)]
    pub feedback: bool,
}

/// Parses `V` or `X,Y` \[m\] into two finite f32 values (`what` names the option).
pub fn parse_pair(what: &str, text: &str) -> crate::Result<[f32; 2]> {
    let values: Vec<&str> = text.split(',').map(str::trim).collect();
    let parse = |s: &str| -> crate::Result<f32> {
        let v: f64 = s
            .parse()
            .map_err(|_| crate::Error::Usage(format!("{what}: `{s}` is not a number (metres)")))?;
        let v = v as f32;
        if v.is_finite() {
            Ok(v)
        } else {
            Err(crate::Error::Usage(format!(
                "{what}: `{s}` is not a finite f32 (metres)"
            )))
        }
    };
    match values.as_slice() {
        [v] => {
            let v = parse(v)?;
            Ok([v, v])
        }
        [x, y] => Ok([parse(x)?, parse(y)?]),
        _ => Err(crate::Error::Refused(format!(
            "{what}: `{text}`: expected one value or two separated by a comma"
        ))),
    }
}

/// The band of `p`, with its tolerance replaced by `tolerance_m` if given (validated).
pub fn band(p: &AxisParams, tolerance_m: Option<f64>) -> crate::Result<OnTarget> {
    match tolerance_m {
        Some(t) => OnTarget::new(t as f32, p.on_target.ticks)
            .map_err(|e| crate::Error::Refused(format!("--tolerance {t}: {e}"))),
        None => Ok(p.on_target),
    }
}

/// One axis of the simulated loop (see the module doc).
struct AxisSim {
    compensator: Compensator,
    state: CompensatorState,
    chain: Option<InverseChain>,
    servo: Option<(Servo, ServoState)>,
    plant: AxisChain,
    plant_state: ModelState,
    plant_effects: piezo_core::effects::EffectsState,
    reading_m: f32,
    previous_reference_m: f32,
    band: OnTarget,
    on_target: OnTargetState,
}

impl AxisSim {
    fn new(
        p: &AxisParams,
        plant: AxisChain,
        sample_period_s: f32,
        band: OnTarget,
        feedback: bool,
        name: &str,
    ) -> crate::Result<Self> {
        let settings = p.settings(sample_period_s).inside_guard();
        let core = |source: piezo_core::ParamError| crate::Error::Params {
            context: name.to_string(),
            source,
        };
        let compensator =
            Compensator::new(p.model(sample_period_s).map_err(core)?, settings).map_err(core)?;
        let u0 = p.limits.output_min_v;
        let chain = InverseChain::single(p.effect_chain(sample_period_s).map_err(core)?, u0);
        let servo = if feedback {
            let params = p.servo.ok_or_else(|| {
                crate::Error::Refused(format!(
                    "--feedback: the stage file has no [{name}.servo] (servo-tune writes one)"
                ))
            })?;
            let servo = Servo::new(params, settings, p.linear_gain_m_per_v).map_err(core)?;
            Some((
                servo,
                ServoState::at_rest(u0, ServoMode::FeedforwardFeedback),
            ))
        } else {
            None
        };
        let AxisChain::Static { model, effects } = plant else {
            return Err(crate::Error::Refused(format!(
                "{name}: the firmware runs static models only"
            )));
        };
        let mut plant_state = ModelState::at_rest(u0);
        let mut plant_effects = piezo_core::effects::EffectsState::at_rest(u0);
        let w = model.step(&mut plant_state, u0);
        effects.forward_z(&mut plant_effects, plant_state.input_v, w);
        let reading_m = effects.output_m(&plant_effects);
        Ok(Self {
            compensator,
            state: CompensatorState::at_rest(u0),
            chain,
            servo,
            plant,
            plant_state,
            plant_effects,
            reading_m,
            previous_reference_m: f32::NAN,
            band,
            on_target: OnTargetState::default(),
        })
    }

    /// One tick tracking `reference_m`; returns whether the axis is on target.
    fn tick(&mut self, reference_m: f32) -> bool {
        let (now, target) = match self.chain.as_mut() {
            Some(c) => {
                let (r, w) = c.next_targets(|| [reference_m, reference_m]);
                (r[0], w[0])
            }
            None => (reference_m, reference_m),
        };
        let u_ff = self
            .compensator
            .compensate(&mut self.state, target)
            .voltage_v;
        let u = match self.servo.as_mut() {
            Some((servo, state)) => {
                servo
                    .step(state, self.previous_reference_m, self.reading_m, u_ff)
                    .voltage_v
            }
            None => u_ff,
        };
        if let Some(c) = self.chain.as_mut() {
            c.commit(0, u, self.compensator.model().output(&self.state.model));
        }
        let on = self.band.observe(
            &mut self.on_target,
            self.reading_m,
            self.previous_reference_m,
        );
        self.previous_reference_m = now;
        if let AxisChain::Static { model, effects } = &self.plant {
            let w = model.step(&mut self.plant_state, u);
            effects.forward_z(&mut self.plant_effects, self.plant_state.input_v, w);
            self.reading_m = effects.output_m(&self.plant_effects);
        }
        on
    }
}

/// The predicted step of both axes: per axis the settling time \[ticks\] (`None`: not on target
/// within `max_ticks`), the ticks until the flag rose, and the band.
#[derive(Debug, Clone, PartialEq)]
pub struct Prediction {
    /// Loop rate \[Hz\].
    pub loop_rate_hz: f64,
    /// Per axis: settling time \[ticks\] of the step to `to`.
    pub settle_ticks: [Option<u32>; 2],
    /// Per axis: ticks from the first reading answering `to` to the flag.
    pub flag_ticks: [Option<u32>; 2],
    /// Per axis: the band used.
    pub band: [OnTarget; 2],
}

/// Simulates the step `from` → `to` \[m\] of `set` (module doc).
pub fn predict(
    set: &FirmwareSet,
    from: [f32; 2],
    to: [f32; 2],
    tolerance_m: Option<f64>,
    timeout_s: f64,
    feedback: bool,
) -> crate::Result<Prediction> {
    let valid = set.file.validate().map_err(crate::Error::from)?;
    let sample_period_s = 1.0 / set.loop_rate_hz;
    let rate = f64::from(set.loop_rate_hz);
    if !(timeout_s > 0.0 && timeout_s * rate <= 1e8) {
        return Err(crate::Error::Refused(format!(
            "--timeout {timeout_s}: expected > 0 s and at most 1e8 ticks"
        )));
    }
    let max_ticks = (timeout_s * rate).ceil() as u32;
    let mut settle_ticks = [None; 2];
    let mut flag_ticks = [None; 2];
    let mut bands = [set.axes[0].on_target; 2];
    for i in 0..2 {
        let name = ["x", "y"][i];
        let p = &set.axes[i];
        let plant = valid.axes.get(i).unwrap_or(&valid.axes[0]).chain;
        bands[i] = band(p, tolerance_m)?;
        let mut sim = AxisSim::new(p, plant, sample_period_s, bands[i], feedback, name)?;
        // The first move, to A, and on target there.
        if !(0..max_ticks).any(|_| sim.tick(from[i])) {
            return Err(crate::Error::Refused(format!(
                "{name} is not on target at --from {} m within {timeout_s} s: no step to time",
                from[i]
            )));
        }
        // The step: the first tick plays X, the next reading answers it.
        sim.tick(to[i]);
        for k in 0..max_ticks {
            if sim.tick(to[i]) {
                flag_ticks[i] = Some(k);
                let s = sim.on_target.settle_ticks();
                settle_ticks[i] = (s != NOT_SETTLED).then_some(s);
                break;
            }
        }
    }
    Ok(Prediction {
        loop_rate_hz: rate,
        settle_ticks,
        flag_ticks,
        band: bands,
    })
}

/// Runs `settle`: JSON on stdout.
pub fn settle_cmd(a: &SettleArgs) -> crate::Result<String> {
    let from = parse_pair("--from", &a.from)?;
    let to = parse_pair("--to", &a.to)?;
    let file = a.params.display().to_string();
    let bytes =
        std::fs::read(&a.params).map_err(|e| crate::Error::Refused(format!("{file}: {e}")))?;
    let set = FirmwareSet::from_bytes(&file, &bytes).map_err(crate::Error::from)?;
    let p = predict(&set, from, to, a.tolerance, a.timeout, a.feedback)?;
    let seconds = |t: Option<u32>| t.map(|t| f64::from(t) / p.loop_rate_hz);
    let value = serde_json::json!({
        "params": file,
        "control": if a.feedback { "feedforward+feedback" } else { "feedforward" },
        "loop_rate_hz": p.loop_rate_hz,
        "from_m": from,
        "to_m": to,
        "tolerance_m": p.band.map(|b| b.tolerance_m),
        "ticks": p.band.map(|b| b.ticks),
        "settle_ticks": p.settle_ticks,
        "settle_s": p.settle_ticks.map(seconds),
        "on_target_ticks": p.flag_ticks,
        "on_target_s": p.flag_ticks.map(seconds),
    });
    if p.settle_ticks.iter().any(Option::is_none) {
        return Err(crate::Error::Refused(format!(
            "not on target at --to within {} s: {value}",
            a.timeout
        )));
    }
    serde_json::to_string(&value).map_err(crate::Error::from)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn built_in() -> FirmwareSet {
        let text = include_str!("../../firmware/params/xy-stage.toml");
        FirmwareSet::from_bytes("xy-stage.toml", text.as_bytes()).unwrap()
    }

    #[test]
    fn positions_are_one_or_two_finite_values() {
        assert_eq!(parse_pair("--to", "2e-6").unwrap(), [2e-6, 2e-6]);
        assert_eq!(parse_pair("--to", "1e-6, 3e-6").unwrap(), [1e-6, 3e-6]);
        for bad in ["", "x", "1e-6,2e-6,3e-6", "1e40", "nan"] {
            let e = parse_pair("--to", bad).unwrap_err().to_string();
            assert!(e.starts_with("--to: "), "{e}");
        }
    }

    /// A slew-limited step: its settling time is at least the ticks the slew limit needs for the
    /// voltage it takes, a wider band settles no later, and a larger step takes longer.
    #[test]
    fn a_step_settles_after_its_slew_and_a_wider_band_no_later() {
        let set = built_in();
        let p = predict(&set, [2e-6; 2], [18e-6; 2], None, 0.5, false).unwrap();
        let t = p.settle_ticks.map(Option::unwrap);
        let a = &set.axes[0];
        // The voltage the step needs at least (the first loading's secant gain is the largest
        // dy/du of the loading branch's chord), at 5 V per tick.
        let per_tick = a.limits.slew_limit_v_per_s / set.loop_rate_hz;
        let span_v = 16e-6 / (a.linear_gain_m_per_v * 2.0);
        assert!(t[0] as f32 >= span_v / per_tick, "{t:?}");
        assert_eq!(p.band[0], a.on_target);
        let wide = predict(&set, [2e-6; 2], [18e-6; 2], Some(1e-6), 0.5, false).unwrap();
        assert!(wide.settle_ticks[0].unwrap() <= t[0]);
        let small = predict(&set, [2e-6; 2], [4e-6; 2], None, 0.5, false).unwrap();
        assert!(small.settle_ticks[0].unwrap() < t[0]);
        assert!(predict(&set, [2e-6; 2], [18e-6; 2], Some(-1.0), 0.5, false)
            .unwrap_err()
            .to_string()
            .contains("--tolerance"));
    }
}
