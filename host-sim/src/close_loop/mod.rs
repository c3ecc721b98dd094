//! `close-loop`: fit the base model, read its residual, name the effect it lacks, add it, refit, repeat;
//! report the error before and after (and on held-out data with `--validate`).
//!
//! 1. Base model: the symmetric Bouc-Wen model y = k1·u + k2·h + y0 fitted by `identify`'s default
//!    method (`vp-de-lm`), per axis.
//! 2. Diagnosis ([`diagnose`]): every effect not yet in the model is screened on the residual (its
//!    regressors fitted by least squares: the share of the residual variance each explains, and initial
//!    values). The (up to four) candidates explaining at least a quarter of `--min-share` are then fitted
//!    for real: the whole model with the effect added, refitted by a short Levenberg–Marquardt run
//!    ([`full`]). The fit with the best Bayesian information criterion
//!    ΔBIC = N·ln(SSE₁/SSE₀) + p·ln N is added if it explains at least `--min-share` of the residual
//!    variance, has ΔBIC < −10 and, after a full refit, lowers the RMS by at least 2 %. Then every
//!    effect added earlier is tried out again: if the model refitted without it is within 2 % of the
//!    RMS, it was a stand-in for the new one and is removed (reported as a `removed` step).
//! 3. Stop when no candidate is accepted or the residual is white (Ljung–Box).
//!
//! The model simulated everywhere is piezo-core's (`StaticModel` + `effects::Effects`), which the
//! firmware runs too; the parameter file written is the firmware's format with an `[x.effects]` table.

pub mod diagnose;
pub mod full;

use crate::identify::model::{to_toml, Identified};
use crate::identify::{fit_block, identify, IdentifySettings, Method, Record};
use crate::plot::{plot_panels, Panel, Series};
use diagnose::{residual_figures, screen, EffectKind, Signals};
use full::{refit, AxisModel, FitData};
use piezo_core::effects::EffectParams;
use serde_json::{json, Value};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Settings of one run.
#[derive(Debug, Clone)]
pub struct CloseLoopSettings {
    /// First scored time \[s\].
    pub start_s: f64,
    /// Smallest share of the residual variance a candidate must explain.
    pub min_share: f64,
    /// Seed of the base identification.
    pub seed: u64,
    /// Only firmware-invertible base sets.
    pub invertible: bool,
    /// Effects that may be added.
    pub allowed: Vec<EffectKind>,
    /// Progress on stderr.
    pub progress: bool,
}

impl Default for CloseLoopSettings {
    fn default() -> Self {
        Self {
            start_s: 0.0,
            min_share: 0.05,
            seed: 1,
            invertible: false,
            allowed: EffectKind::ALL.to_vec(),
            progress: false,
        }
    }
}

/// One axis's outcome.
#[derive(Debug, Clone)]
pub struct AxisOutcome {
    /// Axis name (the output column).
    pub name: String,
    /// The base model.
    pub base: AxisModel,
    /// The final model.
    pub model: AxisModel,
    /// Decision log (JSON steps).
    pub steps: Vec<Value>,
    /// Base prediction and final prediction on the fitted record.
    pub before: Vec<f64>,
    /// Final prediction.
    pub after: Vec<f64>,
}

/// The outcome of a run.
#[derive(Debug, Clone)]
pub struct Outcome {
    /// Per axis.
    pub axes: Vec<AxisOutcome>,
    /// First scored sample.
    pub from: usize,
    /// The report (schema of issue 6).
    pub report: Value,
}

fn log(show: bool, msg: impl AsRef<str>) {
    if show {
        eprintln!("close-loop: {}", msg.as_ref());
    }
}

fn base_model(record: &Record, s: &CloseLoopSettings) -> Result<AxisModel, String> {
    let id = identify(
        record,
        &IdentifySettings {
            model: crate::identify::model::ModelKind::Symmetric,
            method: Method::VpDeLm,
            seed: s.seed,
            start_s: s.start_s,
            no_shift: true,
            invertible: s.invertible,
            progress: s.progress,
        },
    )?;
    let Identified::Static {
        bouc_wen,
        map,
        sample_period_s,
        input_range_v,
        ..
    } = id.set
    else {
        return Err("base identification did not give a static model".into());
    };
    // The range of w given to the effects: the measured range widened by a quarter on each side.
    let (lo, hi) = min_max(&record.y_m);
    let pad = 0.25 * (hi - lo).max(1e-12);
    Ok(AxisModel {
        bouc_wen,
        map,
        effects: EffectParams::default(),
        added: Vec::new(),
        input_range_v,
        w_range_m: ((lo - pad) as f32, (hi + pad) as f32),
        sample_period_s,
    })
}

fn min_max(v: &[f64]) -> (f64, f64) {
    v.iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &x| {
            (a.min(x), b.max(x))
        })
}

/// Runs the loop on one axis; `other_zd` is the other axis's delayed output (two-axis records).
fn close_axis(
    name: &str,
    record: &Record,
    other_zd: Option<&[f64]>,
    s: &CloseLoopSettings,
    base: AxisModel,
) -> Result<AxisOutcome, String> {
    let from = record.index_at(s.start_s);
    let u: Vec<f32> = record.u.iter().map(|&v| v as f32).collect();
    let data = FitData {
        u: &u,
        y: &record.y_m,
        other_zd,
        from,
    };
    let ts = record.sample_period_s();
    let mut model = base.clone();
    let first = model.simulate(&u, other_zd)?;
    let before = first.y.clone();
    let mut sim = first;
    let mut steps = Vec::new();
    let mut current_rms =
        piezo_core::metrics::rms(&record.y_m[from..], &sim.y[from..]).unwrap_or(f64::INFINITY);
    log(
        s.progress,
        format!("{name}: base model rms {:.4e} m", current_rms),
    );
    loop {
        let residual: Vec<f64> = (from..u.len()).map(|k| record.y_m[k] - sim.y[k]).collect();
        let figures = residual_figures(&residual);
        if figures["white"].as_bool() == Some(true) {
            steps.push(json!({"effect": null, "rms": current_rms, "evidence": {"stop": "residual is white (Ljung-Box)", "residual": figures}}));
            break;
        }
        let remaining: Vec<EffectKind> = s
            .allowed
            .iter()
            .copied()
            .filter(|e| !model.added.contains(e))
            .filter(|e| *e != EffectKind::Coupling || other_zd.is_some())
            .collect();
        if remaining.is_empty() {
            break;
        }
        let signals = Signals {
            t_s: &record.t_s,
            u: &record.u,
            y: &record.y_m,
            y_hat: &sim.y,
            h: &sim.h,
            other_y_hat: other_zd,
            from,
            sample_period_s: ts,
        };
        let candidates = screen(&signals, &remaining);
        let ranking: Vec<Value> = candidates
            .iter()
            .map(|c| json!({"effect": c.effect.name(), "share": c.share, "delta_bic": c.delta_bic, "accepted": c.accepted(s.min_share)}))
            .collect();
        // Every candidate the screening does not rule out is fitted for real: the whole model with the
        // effect added, refitted by a short Levenberg-Marquardt run; the decision is on those fits.
        let n_scored = (u.len() - from) as f64;
        let sse0 = current_rms * current_rms * n_scored;
        let mut trials = Vec::new();
        for cand in candidates
            .iter()
            .filter(|c| c.share >= 0.25 * s.min_share)
            .take(4)
        {
            let trial = model.with_effect(cand.init);
            let started = Instant::now();
            let (fitted, sse, evals) = refit(&trial, &data, 20, |_, _| {});
            let p_new = (fitted.encode().0.len() - model.encode().0.len()) as f64;
            let share = if sse.is_finite() {
                (1.0 - sse / sse0).max(0.0)
            } else {
                0.0
            };
            let bic = n_scored * (sse.max(1e-300) / sse0.max(1e-300)).ln() + p_new * n_scored.ln();
            log(
                s.progress,
                format!(
                    "{name}: candidate {}: screening share {:.1} %, refit rms {:.4e} m, share {:.1} %, dBIC {:.0} ({evals} evaluations, {:.1} s)",
                    cand.effect.name(),
                    100.0 * cand.share,
                    (sse / n_scored).sqrt(),
                    100.0 * share,
                    bic,
                    started.elapsed().as_secs_f64()
                ),
            );
            trials.push((cand, fitted, sse, share, bic));
        }
        let trial_log: Vec<Value> = trials
            .iter()
            .map(|(c, _, sse, share, bic)| json!({"effect": c.effect.name(), "refit_rms": (sse / n_scored).sqrt(), "share": share, "delta_bic": bic}))
            .collect();
        let mut added = false;
        if let Some((cand, fitted, _, share, bic)) = trials
            .into_iter()
            .filter(|t| t.3 >= s.min_share && t.4 < -10.0 && t.2.is_finite())
            .min_by(|a, b| a.4.total_cmp(&b.4))
        {
            let started = Instant::now();
            let (fitted, sse, evals) = refit(&fitted, &data, 40, |_, _| {});
            let new_rms = (sse / n_scored).sqrt();
            log(
                s.progress,
                format!(
                    "{name}: added {}: rms {:.4e} -> {:.4e} m ({evals} evaluations, {:.1} s)",
                    cand.effect.name(),
                    current_rms,
                    new_rms,
                    started.elapsed().as_secs_f64()
                ),
            );
            if new_rms.is_finite() && new_rms < 0.98 * current_rms {
                steps.push(json!({
                    "effect": cand.effect.name(),
                    "rms": new_rms,
                    "evidence": {
                        "rms_before_step": current_rms,
                        "share_explained": share,
                        "delta_bic": bic,
                        "screening": cand.evidence,
                        "screening_ranking": ranking,
                        "trial_fits": trial_log.clone(),
                        "residual_before_step": figures,
                    }
                }));
                model = fitted;
                current_rms = new_rms;
                added = true;
                // Backward check: an effect added earlier that the new one makes redundant (its
                // removal, refitted, costs less than 2 % of the RMS) is taken out again.
                let earlier: Vec<EffectKind> = model
                    .added
                    .iter()
                    .copied()
                    .filter(|k| *k != cand.effect)
                    .collect();
                for kind in earlier {
                    let (pruned, sse, evals) =
                        refit(&model.without_effect(kind), &data, 20, |_, _| {});
                    let pruned_rms = (sse / n_scored).sqrt();
                    if pruned_rms.is_finite() && pruned_rms < 1.02 * current_rms {
                        log(
                            s.progress,
                            format!(
                                "{name}: removed {}: redundant after {} (rms {:.4e} m without it)",
                                kind.name(),
                                cand.effect.name(),
                                pruned_rms
                            ),
                        );
                        steps.push(json!({
                            "effect": kind.name(),
                            "removed": true,
                            "rms": pruned_rms,
                            "evidence": {"reason": format!("redundant after adding {}: without it the refitted RMS is within 2 %", cand.effect.name()), "rms_with": current_rms, "refit_evaluations": evals}
                        }));
                        model = pruned;
                        current_rms = pruned_rms;
                    }
                }
                sim = model.simulate(&u, other_zd)?;
            }
        }
        if !added {
            steps.push(json!({"effect": null, "rms": current_rms, "evidence": {"stop": format!("no candidate, fitted, explains {:.0} % of the residual variance with a better BIC (dBIC < -10) and lowers the RMS by 2 %", 100.0 * s.min_share), "screening_ranking": ranking, "trial_fits": trial_log, "residual": figures}}));
            break;
        }
    }
    Ok(AxisOutcome {
        name: name.into(),
        base,
        model,
        steps,
        before,
        after: sim.y,
    })
}

/// Metrics block (rms, max_abs, r2, mrd_percent) over `from..`.
fn metrics(y: &[f64], p: &[f64]) -> Value {
    let f = fit_block(y, p);
    json!({"rms": f["rms"], "max_abs": f["max_abs"], "r2": f["r2"], "mrd_percent": f["mrd_percent"]})
}

/// Concatenates per-axis series for the combined metrics of a two-axis record.
fn joined(parts: &[&[f64]]) -> Vec<f64> {
    parts.iter().flat_map(|p| p.iter().copied()).collect()
}

/// Runs `close-loop` on one record per axis (same times).
pub fn close_loop(records: &[Record], s: &CloseLoopSettings) -> Result<Outcome, String> {
    let from = records[0].index_at(s.start_s);
    let mut bases = Vec::new();
    for (i, r) in records.iter().enumerate() {
        log(s.progress, format!("axis {i}: identifying the base model"));
        bases.push(base_model(r, s)?);
    }
    let mut axes = Vec::new();
    if records.len() == 1 {
        axes.push(close_axis("y", &records[0], None, s, bases[0].clone())?);
    } else {
        let u1: Vec<f32> = records[1].u.iter().map(|&v| v as f32).collect();
        let other = bases[1].simulate(&u1, None)?.zd;
        let x = close_axis("x", &records[0], Some(&other), s, bases[0].clone())?;
        let u0: Vec<f32> = records[0].u.iter().map(|&v| v as f32).collect();
        let other = x.model.simulate(&u0, None)?.zd;
        let y = close_axis("y", &records[1], Some(&other), s, bases[1].clone())?;
        axes.push(x);
        axes.push(y);
    }
    let meas: Vec<&[f64]> = records.iter().map(|r| &r.y_m[from..]).collect();
    let bef: Vec<&[f64]> = axes.iter().map(|a| &a.before[from..]).collect();
    let aft: Vec<&[f64]> = axes.iter().map(|a| &a.after[from..]).collect();
    let mut effects_added: Vec<&str> = Vec::new();
    for a in &axes {
        for e in &a.model.added {
            if !effects_added.contains(&e.name()) {
                effects_added.push(e.name());
            }
        }
    }
    let steps: Vec<Value> = axes
        .iter()
        .flat_map(|a| {
            a.steps.iter().map(move |st| {
                let mut st = st.clone();
                if records.len() > 1 {
                    st["axis"] = json!(a.name);
                }
                st
            })
        })
        .collect();
    let report = json!({
        "unit": "m",
        "samples": records[0].u.len() - from,
        "base_model": "symmetric Bouc-Wen y = k1*u + k2*h + y0 (vp-de-lm)",
        "before": metrics(&joined(&meas), &joined(&bef)),
        "after": metrics(&joined(&meas), &joined(&aft)),
        "effects_added": effects_added,
        "steps": steps,
        "axes": axes.iter().enumerate().map(|(i, a)| json!({
            "axis": a.name,
            "effects_added": a.model.added.iter().map(|e| e.name()).collect::<Vec<_>>(),
            "before": metrics(&records[i].y_m[from..], &a.before[from..]),
            "after": metrics(&records[i].y_m[from..], &a.after[from..]),
            "base_params": params_json(&a.base),
            "params": params_json(&a.model),
        })).collect::<Vec<_>>(),
        "data": records[0].path.display().to_string(),
        "start_s": s.start_s,
    });
    Ok(Outcome { axes, from, report })
}

/// Parameters of an axis model (JSON, SI).
pub fn params_json(m: &AxisModel) -> Value {
    let e = &m.effects;
    json!({
        "bouc_wen": {"a": m.bouc_wen.a, "beta": m.bouc_wen.beta, "gamma": m.bouc_wen.gamma, "n": m.bouc_wen.n},
        "static_map": {"k1_m_per_v": m.map.k1_m_per_v, "k2_m_per_h": m.map.k2_m_per_h, "offset_m": m.map.offset_m},
        "effects": {
            "creep_gain_m_per_v": e.creep_gain_m_per_v, "creep_time_constant_s": e.creep_time_constant_s,
            "even_coefficient_m_per_v2": e.even_coefficient_m_per_v2, "even_center_v": e.even_center_v,
            "mode_frequency_hz": e.mode_frequency_hz, "mode_damping": e.mode_damping,
            "delay_s": e.delay_s, "drift_rate_m_per_s": e.drift_rate_m_per_s, "coupling": e.coupling,
        },
        "input_range_v": [m.input_range_v.0, m.input_range_v.1],
        "sample_period_s": m.sample_period_s,
    })
}

/// Validation: both models predict `records` (the model sees only u), scored from `from`.
pub fn validate(outcome: &Outcome, records: &[Record], start_s: f64) -> Result<Value, String> {
    let from = records[0].index_at(start_s);
    let mut meas = Vec::new();
    let mut bef = Vec::new();
    let mut aft = Vec::new();
    let us: Vec<Vec<f32>> = records
        .iter()
        .map(|r| r.u.iter().map(|&v| v as f32).collect())
        .collect();
    // Two axes: each axis's model couples to the other axis's delayed output of the same model kind.
    let delayed = |final_model: bool| -> Result<Vec<Vec<f64>>, String> {
        if records.len() < 2 {
            return Ok(Vec::new());
        }
        outcome
            .axes
            .iter()
            .zip(&us)
            .map(|(a, u)| {
                let m = if final_model { &a.model } else { &a.base };
                m.simulate(u, None).map(|s| s.zd)
            })
            .collect()
    };
    let (base_zd, final_zd) = (delayed(false)?, delayed(true)?);
    for (i, a) in outcome.axes.iter().enumerate() {
        let other = |z: &[Vec<f64>]| (z.len() > 1).then(|| z[1 - i].clone());
        let b = a.base.simulate(&us[i], other(&base_zd).as_deref())?;
        let f = a.model.simulate(&us[i], other(&final_zd).as_deref())?;
        meas.extend_from_slice(&records[i].y_m[from..]);
        bef.extend_from_slice(&b.y[from..]);
        aft.extend_from_slice(&f.y[from..]);
    }
    Ok(json!({
        "data": records[0].path.display().to_string(),
        "start_s": start_s,
        "samples": records[0].u.len() - from,
        "before": metrics(&meas, &bef),
        "after": metrics(&meas, &aft),
    }))
}

/// The parameter file of the final model: the firmware format (both axes; a one-axis record writes its
/// model to both) with an `[x.effects]` table per axis, and the record's sample rate as the loop rate.
pub fn parameter_file(outcome: &Outcome, data: &str, start_s: f64) -> String {
    let a0 = &outcome.axes[0];
    let set = Identified::Static {
        bouc_wen: a0.model.bouc_wen,
        map: a0.model.map,
        asymmetry: Default::default(),
        sample_period_s: a0.model.sample_period_s,
        input_range_v: a0.model.input_range_v,
    };
    let mut text = to_toml(&set, "close-loop", data, start_s);
    // The effects are discretised at the loop rate; the record's rate is the one they were identified
    // at (and a delay must fit in 64 loop periods).
    let rate_hz = (1e3 / f64::from(a0.model.sample_period_s)).round() / 1e3;
    text = text.replacen(
        "loop_rate_hz = 10000.0\n",
        &format!(
            "# close-loop: the record's sample rate, at which the effects were identified\nloop_rate_hz = {rate_hz:?}\n"
        ),
        1,
    );
    if outcome.axes.len() > 1 {
        // Replace the y axis tables with the second axis's model.
        let a1 = &outcome.axes[1];
        let set1 = Identified::Static {
            bouc_wen: a1.model.bouc_wen,
            map: a1.model.map,
            asymmetry: Default::default(),
            sample_period_s: a1.model.sample_period_s,
            input_range_v: a1.model.input_range_v,
        };
        let t1 = to_toml(&set1, "close-loop", data, start_s);
        if let (Some(i0), Some(i1)) = (text.find("[y.bouc_wen]"), t1.find("[y.bouc_wen]")) {
            text.truncate(i0);
            text.push_str(&t1[i1..]);
        }
    }
    for (i, axis) in ["x", "y"].iter().enumerate() {
        let m = &outcome.axes[i.min(outcome.axes.len() - 1)].model;
        let e = &m.effects;
        let list = |v: &[f32]| {
            v.iter()
                .map(|x| format!("{x:?}"))
                .collect::<Vec<_>>()
                .join(", ")
        };
        text.push_str(&format!(
            "\n[{axis}.effects]\n# added by close-loop: {}\ncreep_gain_m_per_v = [{}]\ncreep_time_constant_s = [{}]\n\
             even_coefficient_m_per_v2 = {:?}\neven_center_v = {:?}\nmode_frequency_hz = {:?}\nmode_damping = {:?}\n\
             delay_s = {:?}\ndrift_rate_m_per_s = {:?}\ncoupling = {:?}\n",
            m.added.iter().map(|e| e.name()).collect::<Vec<_>>().join(", "),
            list(&e.creep_gain_m_per_v),
            list(&e.creep_time_constant_s),
            e.even_coefficient_m_per_v2,
            e.even_center_v,
            e.mode_frequency_hz,
            e.mode_damping,
            e.delay_s,
            e.drift_rate_m_per_s,
            e.coupling,
        ));
    }
    text
}

/// Writes the plots of the residual before and after (time, against u, spectrum) and the loops.
pub fn write_plots(
    outcome: &Outcome,
    records: &[Record],
    dir: &Path,
    formats: &[&str],
) -> Result<Vec<String>, String> {
    std::fs::create_dir_all(dir).map_err(|e| format!("--plots {}: {e}", dir.display()))?;
    let from = outcome.from;
    let mut written = Vec::new();
    for (i, a) in outcome.axes.iter().enumerate() {
        let r = &records[i];
        let ts = r.sample_period_s();
        let res =
            |p: &[f64]| -> Vec<f64> { (from..p.len()).map(|k| (r.y_m[k] - p[k]) * 1e6).collect() };
        let rb = res(&a.before);
        let ra = res(&a.after);
        let t: Vec<f64> = r.t_s[from..].to_vec();
        let u: Vec<f64> = r.u[from..].to_vec();
        let pts =
            |x: &[f64], y: &[f64]| x.iter().copied().zip(y.iter().copied()).collect::<Vec<_>>();
        let spec = |v: &[f64]| -> Vec<(f64, f64)> {
            diagnose::spectrum(v, ts)
                .into_iter()
                .filter(|p| p.1 > 0.0)
                .map(|(f, m)| (f.log10(), m.log10()))
                .collect()
        };
        let effects = a
            .model
            .added
            .iter()
            .map(|e| e.name())
            .collect::<Vec<_>>()
            .join(" + ");
        let after_name = format!(
            "after (+ {})",
            if effects.is_empty() {
                "nothing"
            } else {
                &effects
            }
        );
        let panels = vec![
            Panel {
                title: format!("{}: residual in time", a.name),
                x_label: "t [s]".into(),
                y_label: "residual [um]".into(),
                series: vec![
                    Series::line("before (base model)", pts(&t, &rb), 4000),
                    Series::line(after_name.clone(), pts(&t, &ra), 4000),
                ],
            },
            Panel {
                title: format!("{}: residual against the input", a.name),
                x_label: "u [V]".into(),
                y_label: "residual [um]".into(),
                series: vec![
                    Series::line("before", pts(&u, &rb), 4000),
                    Series::line(after_name.clone(), pts(&u, &ra), 4000),
                ],
            },
            Panel {
                title: format!("{}: residual amplitude spectrum", a.name),
                x_label: "log10 f [Hz]".into(),
                y_label: "log10 amplitude [um]".into(),
                series: vec![
                    Series::line("before", spec(&rb), 1000),
                    Series::line(after_name.clone(), spec(&ra), 1000),
                ],
            },
            Panel {
                title: format!("{}: loops", a.name),
                x_label: "u [V]".into(),
                y_label: "y [um]".into(),
                series: vec![
                    Series::line(
                        "measured",
                        pts(
                            &u,
                            &r.y_m[from..].iter().map(|v| v * 1e6).collect::<Vec<_>>(),
                        ),
                        4000,
                    ),
                    Series::line(
                        "base model",
                        pts(
                            &u,
                            &a.before[from..].iter().map(|v| v * 1e6).collect::<Vec<_>>(),
                        ),
                        4000,
                    ),
                    Series::line(
                        after_name.clone(),
                        pts(
                            &u,
                            &a.after[from..].iter().map(|v| v * 1e6).collect::<Vec<_>>(),
                        ),
                        4000,
                    ),
                ],
            },
        ];
        for ext in formats {
            let path = dir.join(format!("close-loop-{}.{ext}", a.name));
            plot_panels(&path, &panels).map_err(|e| e.to_string())?;
            written.push(path.display().to_string());
        }
    }
    Ok(written)
}

/// Arguments of `close-loop`.
#[derive(Debug, clap::Args)]
#[command(after_help = "\
Fits the symmetric Bouc-Wen model (identify's vp-de-lm), then repeatedly screens the residual for the \
effects creep, drift, delay, asymmetry, dynamics and (two-axis records) coupling, adds the one explaining \
the largest share of the residual variance (at least --min-share, with a better BIC), refits the whole \
model by Levenberg-Marquardt, and stops when nothing is accepted or the residual is white. Every decision \
and its evidence goes into the report. Two-axis records: --u ux_V,uy_V --y x_m,y_m.")]
pub struct CloseLoopArgs {
    /// Record to fit (CSV with unit-suffixed columns).
    #[arg(long)]
    pub data: PathBuf,
    /// Time column (default: first `t_*`).
    #[arg(long)]
    pub t: Option<String>,
    /// Input column(s), comma-separated for two axes (default: first `u_*`).
    #[arg(long)]
    pub u: Option<String>,
    /// Output column(s), comma-separated for two axes (default: first `y_*`).
    #[arg(long)]
    pub y: Option<String>,
    /// First scored time [s]; earlier samples only warm the model up.
    #[arg(long, default_value_t = 0.0)]
    pub start: f64,
    /// Last time used for the fit [s].
    #[arg(long)]
    pub end: Option<f64>,
    /// Held-out record both models predict (same columns); may be the same file with --validate-start.
    #[arg(long)]
    pub validate: Option<PathBuf>,
    /// First scored time of the validation record [s].
    #[arg(long, default_value_t = 0.0)]
    pub validate_start: f64,
    /// Smallest share of the residual variance an effect must explain to be added.
    #[arg(long, default_value_t = 0.05)]
    pub min_share: f64,
    /// Seed of the base identification.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Only base sets the firmware's compensator accepts (strictly monotone map).
    #[arg(long)]
    pub invertible: bool,
    /// Report JSON to write.
    #[arg(long)]
    pub report: PathBuf,
    /// Parameter file of the final model (default: the report's path with .toml).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Directory for the plots (SVG and PNG).
    #[arg(long)]
    pub plots: Option<PathBuf>,
}

/// Reads one record per axis.
pub fn read_records(
    data: &Path,
    t: Option<&str>,
    u: Option<&str>,
    y: Option<&str>,
    end: Option<f64>,
) -> Result<Vec<Record>, String> {
    let split = |s: Option<&str>| -> Vec<Option<String>> {
        match s {
            None => vec![None],
            Some(s) => s.split(',').map(|c| Some(c.trim().to_string())).collect(),
        }
    };
    let us = split(u);
    let ys = split(y);
    if us.len() != ys.len() || us.len() > 2 {
        return Err(format!(
            "--u and --y must name the same number of columns (1 or 2); got {} and {}",
            us.len(),
            ys.len()
        ));
    }
    let mut out = Vec::new();
    for (u, y) in us.iter().zip(&ys) {
        let mut r = Record::read(data, t, u.as_deref(), y.as_deref())
            .map_err(|e| format!("--data: {e}"))?;
        if let Some(end) = end {
            r.cut_after(end)?;
        }
        out.push(r);
    }
    Ok(out)
}

/// Runs `close-loop`.
pub fn close_loop_cmd(a: &CloseLoopArgs) -> Result<String, String> {
    if !(a.min_share > 0.0 && a.min_share < 1.0) {
        return Err(format!("--min-share {}: must be in (0, 1)", a.min_share));
    }
    let records = read_records(
        &a.data,
        a.t.as_deref(),
        a.u.as_deref(),
        a.y.as_deref(),
        a.end,
    )?;
    let settings = CloseLoopSettings {
        start_s: a.start,
        min_share: a.min_share,
        seed: a.seed,
        invertible: a.invertible,
        progress: true,
        ..Default::default()
    };
    let started = Instant::now();
    let mut outcome = close_loop(&records, &settings)?;
    if let Some(v) = &a.validate {
        let vr = read_records(v, a.t.as_deref(), a.u.as_deref(), a.y.as_deref(), None)
            .map_err(|e| e.replace("--data", "--validate"))?;
        outcome.report["validation"] = validate(&outcome, &vr, a.validate_start)?;
    }
    outcome.report["seconds"] = json!(started.elapsed().as_secs_f64());
    let out = a
        .out
        .clone()
        .unwrap_or_else(|| a.report.with_extension("toml"));
    for p in [&a.report, &out] {
        if let Some(dir) = p.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).map_err(|e| format!("{}: {e}", dir.display()))?;
        }
    }
    let text = parameter_file(&outcome, &a.data.display().to_string(), a.start);
    std::fs::write(&out, &text).map_err(|e| format!("--out {}: {e}", out.display()))?;
    outcome.report["params_file"] = json!(out.display().to_string());
    let firmware =
        match crate::identify::firmware_check(&out.display().to_string(), text.as_bytes()) {
            Ok(()) => "accepted by the firmware's parameter check".to_string(),
            Err(e) => format!("REFUSED by the firmware's parameter check: {e}"),
        };
    outcome.report["params_file_firmware_check"] = json!(firmware);
    let json = serde_json::to_string_pretty(&outcome.report).map_err(|e| e.to_string())?;
    std::fs::write(&a.report, json).map_err(|e| format!("--report {}: {e}", a.report.display()))?;
    let mut plots = Vec::new();
    if let Some(dir) = &a.plots {
        plots = write_plots(&outcome, &records, dir, &["svg", "png"])?;
    }
    let r = &outcome.report;
    let mut line = format!(
        "close-loop {}: rms {:.4e} -> {:.4e} m, effects added: [{}]",
        a.data.display(),
        r["before"]["rms"].as_f64().unwrap_or(f64::NAN),
        r["after"]["rms"].as_f64().unwrap_or(f64::NAN),
        r["effects_added"]
            .as_array()
            .map(|v| v
                .iter()
                .filter_map(|e| e.as_str())
                .collect::<Vec<_>>()
                .join(", "))
            .unwrap_or_default()
    );
    if let Some(v) = r.get("validation") {
        line.push_str(&format!(
            "; validation rms {:.4e} -> {:.4e} m",
            v["before"]["rms"].as_f64().unwrap_or(f64::NAN),
            v["after"]["rms"].as_f64().unwrap_or(f64::NAN)
        ));
    }
    line.push_str(&format!(
        "; {} and {} written ({firmware})",
        a.report.display(),
        out.display()
    ));
    if !plots.is_empty() {
        line.push_str(&format!(", {} plots", plots.len()));
    }
    Ok(line)
}
