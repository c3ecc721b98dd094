//! `host-sim simulate`: one of the reference plants (`piezo-reference`) under a signal, with the
//! effects it carries, written as CSV (and optionally plotted). The model under test is not
//! involved.

use crate::csv::write_csv;
use crate::effects::Effects;
use crate::plant::PlantKind;
use crate::signal::{SignalKind, SignalSpec};
use crate::sim::{simulate, SimOutput, SimSettings};
use std::path::PathBuf;

/// Arguments of `simulate`.
#[derive(Debug, clap::Args)]
pub struct SimulateArgs {
    /// Plant: nac2024, stage, xy-stage, bipolar-stack, relaxing-stack, relaxing-stack-shaped, relaxing-stack-stiff.
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
pub fn simulate_cmd(a: &SimulateArgs) -> crate::Result<String> {
    // Refuse an unknown plot format before the simulation runs.
    if let Some(path) = &a.plot {
        crate::plot::Format::of_path(path)
            .map_err(|e| crate::Error::Usage(format!("--plot: {e}")))?;
    }
    let mut plant =
        PlantKind::from_name(&a.plant).map_err(|e| crate::Error::Usage(format!("--plant: {e}")))?;
    let spec =
        SignalSpec::parse(&a.signal).map_err(|e| crate::Error::Usage(format!("--signal: {e}")))?;
    let mut effects = Effects::default();
    for e in &a.effects {
        effects
            .add_spec(e)
            .map_err(|err| crate::Error::Usage(format!("--effect {e}: {err}")))?;
    }
    effects
        .apply_to_plant(&mut plant)
        .map_err(|e| crate::Error::Usage(format!("--effect: {e}")))?;
    let p = plant.as_plant();
    let signals = spec
        .build(p.input_names().len())
        .map_err(|e| crate::Error::Usage(format!("--signal: {e}")))?;
    let settings = SimSettings::new(
        spec.sample_rate_hz.unwrap_or(p.default_sample_rate_hz()),
        spec.duration_s.unwrap_or(spec.default_duration_s()),
    );
    if let Some(duration_s) = spec.duration_s {
        if let Some(w) = csv_length_warning(&spec, duration_s, "duration=") {
            eprintln!("warning: {w}");
        }
    }
    let out = simulate(p, signals, &effects, &settings)
        .map_err(|e| crate::Error::Usage(format!("simulate: {e}")))?;
    write_csv(&a.out, &out.to_table()).map_err(|e| crate::Error::Usage(format!("--out: {e}")))?;
    if let Some(path) = &a.plot {
        crate::plot::plot_simulation(path, &out, p.name())
            .map_err(|e| crate::Error::Usage(format!("--plot: {e}")))?;
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

/// When a `csv` signal's file ends before or after the `duration_s` it is played for (given as
/// `given`, e.g. `duration=` or `--duration`): what happens, naming the file, its length (samples
/// and seconds: its last time plus its last step) and the duration. `None` for the other kinds and
/// when the two agree to 1 ppm.
pub fn csv_length_warning(spec: &SignalSpec, duration_s: f64, given: &str) -> Option<String> {
    let SignalKind::Csv { path, end_s, .. } = &spec.kind else {
        return None;
    };
    // To the nanosecond, so that 100 samples at 1 kHz read 0.1 s.
    let end_s = (end_s * 1e9).round() / 1e9;
    if (duration_s - end_s).abs() <= 1e-6 * end_s.abs().max(duration_s.abs()) {
        return None;
    }
    let samples = crate::csv::read_rows(path)
        .map(|r| format!("{} samples, ", r.lines.len()))
        .unwrap_or_default();
    let file = format!("{} ({samples}{end_s} s)", path.display());
    Some(if duration_s < end_s {
        format!(
            "--signal csv: {file} is longer than {given}{duration_s} s: only its first \
             {duration_s} s are played (without a duration, the whole file)"
        )
    } else {
        format!(
            "--signal csv: {file} is shorter than {given}{duration_s} s: its last sample is held \
             from {end_s} s to {duration_s} s"
        )
    })
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

#[cfg(test)]
mod tests {
    use super::*;

    /// A file of 100 samples at 1 kHz plays 0.1 s: a shorter or longer duration is named with
    /// the file, its length and the duration; the same length, or another kind of signal, is not.
    #[test]
    fn a_csv_signal_of_another_length_than_its_duration_says_so() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("drive.csv");
        let rows: String = (0..100)
            .map(|k| format!("{},{}\n", k as f64 * 1e-3, k))
            .collect();
        std::fs::write(&path, format!("t_s,u_V\n{rows}")).unwrap();
        let spec = SignalSpec::parse(&format!("csv:path={}", path.display())).unwrap();
        let name = path.display().to_string();
        let longer = csv_length_warning(&spec, 0.05, "duration=").unwrap();
        assert!(
            longer.contains(&name)
                && longer.contains("100 samples, 0.1 s")
                && longer.contains("longer than duration=0.05 s"),
            "{longer}"
        );
        let shorter = csv_length_warning(&spec, 0.3, "--duration ").unwrap();
        assert!(
            shorter.contains(&name)
                && shorter.contains("100 samples, 0.1 s")
                && shorter.contains("shorter than --duration 0.3 s")
                && shorter.contains("held"),
            "{shorter}"
        );
        assert_eq!(csv_length_warning(&spec, 0.1, "duration="), None);
        let sine = SignalSpec::parse("sine:amp=1,duration=2").unwrap();
        assert_eq!(csv_length_warning(&sine, 5.0, "duration="), None);
    }
}
