//! `host-sim simulate`: one of the reference plants (`piezo-reference`) under a signal, with the
//! effects it carries, written as CSV (and optionally plotted). The model under test is not
//! involved.

use crate::csv::write_csv;
use crate::effects::Effects;
use crate::plant::PlantKind;
use crate::signal::SignalSpec;
use crate::sim::{simulate, SimOutput, SimSettings};
use std::path::PathBuf;

/// Arguments of `simulate`.
#[derive(Debug, clap::Args)]
pub struct SimulateArgs {
    /// Plant: nac2024, stage, xy-stage, bipolar-stack, relaxing-stack, relaxing-stack-shaped.
    #[arg(long)]
    pub plant: String,
    /// Signal spec in stack volts, e.g.
    /// `sine:amp=10,offset=10,freq=2,phase_deg=-90,duration=1,rate=10000`.
    #[arg(long)]
    pub signal: String,
    /// Effect spec, repeatable, e.g. `creep:tau=0.1/1/10,weight=0.01/0.01/0.01`.
    #[arg(long = "effect")]
    pub effects: Vec<String>,
    /// Output CSV file.
    #[arg(long)]
    pub out: PathBuf,
    /// Optional plot (time series and loop): `.svg` or `.png`, as the extension says.
    #[arg(long)]
    pub plot: Option<PathBuf>,
}

/// `host-sim simulate`: the plant under the signal with the effects; writes the CSV and the plot.
pub fn simulate_cmd(a: &SimulateArgs) -> Result<String, String> {
    // Refuse an unknown plot format before the simulation runs.
    if let Some(path) = &a.plot {
        crate::plot::Format::of_path(path).map_err(|e| format!("--plot: {e}"))?;
    }
    let mut plant = PlantKind::from_name(&a.plant).map_err(|e| format!("--plant: {e}"))?;
    let spec = SignalSpec::parse(&a.signal).map_err(|e| format!("--signal: {e}"))?;
    let mut effects = Effects::default();
    for e in &a.effects {
        effects
            .add_spec(e)
            .map_err(|err| format!("--effect {e}: {err}"))?;
    }
    effects
        .apply_to_plant(&mut plant)
        .map_err(|e| format!("--effect: {e}"))?;
    let p = plant.as_plant();
    let signals = spec
        .build(p.input_names().len())
        .map_err(|e| format!("--signal: {e}"))?;
    let settings = SimSettings::new(
        spec.sample_rate_hz.unwrap_or(p.default_sample_rate_hz()),
        spec.duration_s.unwrap_or(spec.default_duration_s()),
    );
    if let (Some(end_s), Some(duration_s)) = (spec.csv_end_s(), spec.duration_s) {
        if duration_s < end_s {
            eprintln!(
                "note: --signal duration={duration_s}: plays {duration_s} s of the file's {end_s} s \
                 (without duration, the whole file)"
            );
        } else if duration_s > end_s {
            eprintln!(
                "note: --signal duration={duration_s}: the file's samples end at {end_s} s; its \
                 last sample is held to {duration_s} s"
            );
        }
    }
    let out = simulate(p, signals, &effects, &settings).map_err(|e| format!("simulate: {e}"))?;
    write_csv(&a.out, &out.to_table()).map_err(|e| format!("--out: {e}"))?;
    if let Some(path) = &a.plot {
        crate::plot::plot_simulation(path, &out, p.name()).map_err(|e| format!("--plot: {e}"))?;
    }
    Ok(format!(
        "{}: {} samples at {} Hz written to {} ({})",
        p.name(),
        out.t_s.len(),
        settings.sample_rate_hz,
        a.out.display(),
        propagation(&out)
    ))
}

/// How the run moved its state: holds propagated exactly, Dormand–Prince steps, or both.
fn propagation(out: &SimOutput) -> String {
    let steps = format!(
        "{} integrator steps, {} rejected",
        out.stats.accepted, out.stats.rejected
    );
    match out.exact_segments {
        0 => steps,
        n if out.stats.accepted + out.stats.rejected == 0 => {
            format!("{n} exact holds, 0 integrator steps")
        }
        n => format!("{n} exact holds, {steps}"),
    }
}
