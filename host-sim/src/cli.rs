//! Command line (clap derive). `main.rs` only calls [`run`]. Subcommands: `simulate` now; `demo`,
//! `reproduce` and `identify` are to be added to [`Command`] later.

use crate::csv::write_csv;
use crate::effects::{Effects, EFFECT_HELP};
use crate::plant::{PlantKind, PLANT_NAMES};
use crate::signal::{SignalSpec, SIGNAL_HELP};
use crate::sim::{simulate, SimSettings};
use clap::{Parser, Subcommand};
use std::path::PathBuf;

/// Simulated piezo plants (independent f64 reference for the compensator).
#[derive(Debug, Parser)]
#[command(name = "host-sim", version, about)]
pub struct Cli {
    /// What to do.
    #[command(subcommand)]
    pub command: Command,
}

/// Subcommands.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Simulate a plant under a signal with optional effects; write CSV and optionally an SVG plot.
    #[command(after_help = format!(
        "Plants: {PLANT_NAMES}\n  nac2024   Noliac NAC2024 actuator (seed 000), output y_m, 2.56 MHz default rate\n  stage     asymmetric stage (seed 001, Case III; stage-case1/stage-case2 too), output y_m, 10 kHz\n  xy-stage  two-axis flexure stage (seed 002), inputs ux_V/uy_V, outputs x_m/y_m, 10 kHz\n\n{SIGNAL_HELP}\n\n{EFFECT_HELP}"
    ))]
    Simulate(SimulateArgs),
}

/// Arguments of `simulate`.
#[derive(Debug, clap::Args)]
pub struct SimulateArgs {
    /// Plant: nac2024, stage, xy-stage.
    #[arg(long)]
    pub plant: String,
    /// Signal spec, e.g. `sine:amp=10,offset=10,freq=2,phase_deg=-90,duration=1,rate=10000`.
    #[arg(long)]
    pub signal: String,
    /// Effect spec, repeatable, e.g. `creep:tau=0.1/1/10,weight=0.01/0.01/0.01`.
    #[arg(long = "effect")]
    pub effects: Vec<String>,
    /// Output CSV file.
    #[arg(long)]
    pub out: PathBuf,
    /// Optional SVG plot (time series and loop).
    #[arg(long)]
    pub plot: Option<PathBuf>,
}

/// Runs a parsed command line; errors are returned as messages that name the argument at fault.
pub fn run(cli: Cli) -> Result<String, String> {
    match cli.command {
        Command::Simulate(a) => simulate_cmd(&a),
    }
}

fn simulate_cmd(a: &SimulateArgs) -> Result<String, String> {
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
    let out = simulate(p, signals, &effects, &settings).map_err(|e| format!("simulate: {e}"))?;
    write_csv(&a.out, &out.to_table()).map_err(|e| format!("--out: {e}"))?;
    if let Some(path) = &a.plot {
        crate::plot::plot_svg(path, &out, p.name()).map_err(|e| format!("--plot: {e}"))?;
    }
    Ok(format!(
        "{}: {} samples at {} Hz written to {} ({} steps, {} rejected)",
        p.name(),
        out.t_s.len(),
        settings.sample_rate_hz,
        a.out.display(),
        out.stats.accepted,
        out.stats.rejected
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::CommandFactory;

    fn args(plant: &str, signal: &str, effects: &[&str], out: &std::path::Path) -> Cli {
        let mut v = vec!["host-sim", "simulate", "--plant", plant, "--signal", signal];
        for e in effects {
            v.extend(["--effect", e]);
        }
        let o = out.to_str().unwrap_or("x.csv");
        v.extend(["--out", o]);
        Cli::try_parse_from(v).unwrap()
    }

    #[test]
    fn help_lists_plants_signals_effects() {
        let mut cmd = Cli::command();
        let help = cmd
            .find_subcommand_mut("simulate")
            .unwrap()
            .render_long_help()
            .to_string();
        for word in [
            "nac2024",
            "xy-stage",
            "staircase",
            "raster",
            "creep",
            "second-mode",
            "duration=",
        ] {
            assert!(help.contains(word), "help lacks {word}");
        }
    }

    #[test]
    fn errors_name_the_argument_and_choices() {
        let out = std::env::temp_dir().join(format!("host_sim_cli_{}.csv", std::process::id()));
        let e = run(args("nac", "sine", &[], &out)).unwrap_err();
        assert!(e.starts_with("--plant") && e.contains("xy-stage"), "{e}");
        let e = run(args("stage", "sine:freq=fast", &[], &out)).unwrap_err();
        assert!(e.starts_with("--signal") && e.contains("fast"), "{e}");
        let e = run(args("stage", "sine", &["creeep"], &out)).unwrap_err();
        assert!(e.starts_with("--effect") && e.contains("drift"), "{e}");
        let e = run(args("stage", "sine", &["coupling"], &out)).unwrap_err();
        assert!(e.contains("xy-stage only"), "{e}");
    }

    #[test]
    fn simulate_writes_csv_and_svg() {
        let dir = std::env::temp_dir().join(format!("host_sim_cli_run_{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let out = dir.join("xy.csv");
        let mut cli = args(
            "xy-stage",
            "raster:x_high=50,y_high=20,line_freq=10,duration=0.2,rate=2000",
            &[],
            &out,
        );
        let Command::Simulate(a) = &mut cli.command;
        a.plot = Some(dir.join("xy.svg"));
        run(cli).unwrap();
        let t = crate::csv::read_csv(&out).unwrap();
        assert_eq!(t.names, ["t_s", "ux_V", "uy_V", "x_m", "y_m"]);
        assert_eq!(t.rows(), 400);
        let svg = std::fs::read_to_string(dir.join("xy.svg")).unwrap();
        assert!(svg.contains("<svg") && svg.contains("hysteresis loop"));
    }
}
