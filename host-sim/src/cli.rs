//! Command line (clap derive). `main.rs` only calls [`run`]. Subcommands ([`Command`]):
//! `simulate`, `demo`, `reproduce`, `capture`, `identify`, `predict`, `close-loop`,
//! `compensate`, `link`, `servo-bench`, `servo-tune`. Progress goes to stderr, the result (table
//! or summary) to stdout.

use crate::effects::EFFECT_HELP;
use crate::plant::PLANT_NAMES;
use crate::signal::SIGNAL_HELP;
use clap::{Parser, Subcommand};

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
    /// Simulate a plant under a signal in stack volts (V) with optional effects; write the CSV of
    /// its displacement in metres (t_s, u_V, y_m) and optionally a plot (SVG or PNG).
    #[command(after_help = format!(
        "Plants: {PLANT_NAMES}\n  nac2024   Noliac NAC2024 actuator (seed 000), output y_m, 2.56 MHz default rate\n  stage     asymmetric stage (seed 001, Case III; stage-case1/stage-case2 too), output y_m, 10 kHz\n  xy-stage  two-axis flexure stage (seed 002), inputs ux_V/uy_V, outputs x_m/y_m, 10 kHz\n  bipolar-stack   ±100 V stack, hysteresis behind a spread of dielectric relaxations, 740 Hz mode, output y_m, 10 kHz\n  relaxing-stack  ±100 V stack whose whole strain relaxes (loops widen with rate), 740 Hz mode, output y_m, 10 kHz\n  relaxing-stack-shaped  the same with a second, fast-saturating switching population (a loop-shape error no core form has)\n  relaxing-stack-stiff   the relaxing stack with its mode at 7.4 kHz (a mount ten times stiffer)\n\n{SIGNAL_HELP}\n\n{EFFECT_HELP}"
    ))]
    Simulate(crate::simulate::SimulateArgs),
    /// The whole story on the XY stage with creep no model declares: identify, compensate, find the
    /// residual (close-loop), add the effect, compensate again; prints tracking error per axis and
    /// mode (RMS in m and % of stroke), writes plots, demo.csv, demo-params.toml and summary.json.
    #[command(
        after_help = "The plant is host-sim's f64 XY stage (seed 002) with --plant-effect (default: Kelvin-Voigt creep \
tau 0.1/1 s, weights 0.02/0.02, and 2 nm sensor noise), driven through a zero-order-hold DAC at --rate. \
1. identification experiment: raised cosines 0-120 V (x 1 Hz, y 0.7 Hz) for --identify seconds; \
2. close-loop on that record (symmetric Bouc-Wen base, firmware-invertible; effects found from the residual); \
3. tracking a triangle per axis: best affine feed-forward u = (r - c)/g; piezo-core's compensator with the \
identified base model; the same after the core's inverse chain of the effects close-loop added. \
All modes command one sample ahead. Output window 0-120 V."
    )]
    Demo(crate::demo::DemoArgs),
    /// Reproduces the papers' figures with the simulated plants and the piezo-core models: writes
    /// DIR/reproduce.json (each figure in the paper's own unit: µm, % or none, with the paper's value
    /// beside it) and plots.
    #[command(
        after_help = "Sections:\n  xy_stage  loop openings at 120 V and 12 V staircases and maximum displacement (seed 002)\n  nac2024   R^2 and MRD of the core DynamicModel (Table 1, f32, 2.56 MHz, range +-10 V, state limit 10) against the plant with a second mode and a 10 % heavier mass, 10-200 kHz sines of 9.738 V, next to Table 2 (seed 000)\n  stage     RAE and AFV of the standard and asymmetric core models on the stage plant, Cases I-III (seed 001)"
    )]
    Reproduce(crate::reproduce::ReproduceArgs),
    /// Decoded firmware log (QEMU output, or defmt from probe-rs run / defmt-print) to the CSV
    /// that `identify` reads (t_s in s, u_V in V, y_m in m); sequence gaps stop it (--allow-gaps:
    /// kept and marked).
    #[command(after_help = crate::capture::HELP)]
    Capture(crate::capture::CaptureArgs),
    /// Fits a piezo-core model to a record (t in s, u in V, y in m, or the unit its column suffix
    /// names); writes the parameter file (SI units) and a summary JSON.
    Identify(crate::identify::IdentifyArgs),
    /// Simulates an identified model on a record (it sees only u, in V) and reports the fit (RMS
    /// in m).
    Predict(crate::identify::PredictArgs),
    /// Fits the base model, finds the effect its residual lacks (creep, drift, delay, asymmetry,
    /// dynamics, coupling), adds it, refits and repeats; reports the error (RMS in m) before and
    /// after.
    CloseLoop(crate::close_loop::CloseLoopArgs),
    /// The voltages the firmware commands for a reference record (stage file + CSV of metres → CSV
    /// of stack volts per tick, for a wave table or any DAC).
    #[command(after_help = crate::compensate::HELP)]
    Compensate(crate::compensate::CompensateArgs),
    /// Drives the firmware over its command link (QEMU image on a TCP port, or the board's
    /// serial device): status, excite in stack volts and record, upload a stage file, track a
    /// reference in metres, rearm.
    Link(crate::link::LinkArgs),
    /// Open loop, feedforward, feedback and both on the XY stage with creep, drift, noise and
    /// quantisation: tracking error per mode and frequency (% of stroke), closed-loop bandwidth
    /// (Hz); writes DIR/servo.json and plots.
    #[command(after_help = crate::servo_bench::HELP)]
    ServoBench(crate::servo_bench::ServoBenchArgs),
    /// The settling time (s) the stage file's model predicts for a step in metres (the firmware's
    /// compensator, and its servo with --feedback, on the file's forward model; the firmware's
    /// on-target rule); JSON on stdout.
    Settle(crate::settle::SettleArgs),
    /// Tunes the feedback servo of each axis from the stage file's model and the stage's first
    /// mode; writes the stage file with `[x.servo]`/`[y.servo]` and prints the margins (crossover in
    /// Hz, phase margin in degrees).
    ServoTune(crate::servo_tune::ServoTuneArgs),
    /// One step of iterative learning control: reference (m), command (V) and measured record (m)
    /// of a trial → the next trial's command in stack volts (a table tied to its reference and
    /// stage file) and a report.
    #[command(after_help = crate::learn::HELP)]
    Learn(crate::learn::LearnArgs),
    /// Iterative learning control on the XY stage (learned, learned+feedback; 1, 10, 100 Hz;
    /// perturbed stage files): error per trial (% of stroke); writes DIR/learn.json and the plot.
    #[command(after_help = crate::learn_bench::HELP)]
    LearnBench(crate::learn_bench::LearnBenchArgs),
}

/// Runs a parsed command line; errors are returned as messages that name the argument at fault.
pub fn run(cli: Cli) -> crate::Result<String> {
    match cli.command {
        Command::Simulate(a) => crate::simulate::simulate_cmd(&a),
        Command::Demo(a) => crate::demo::demo_cmd(&a),
        Command::Reproduce(a) => crate::reproduce::reproduce_cmd(&a),
        Command::Capture(a) => crate::capture::run(&a, &mut crate::progress),
        Command::Identify(a) => crate::identify::identify_cmd(&a),
        Command::Predict(a) => crate::identify::predict_cmd(&a),
        Command::CloseLoop(a) => crate::close_loop::close_loop_cmd(&a),
        Command::Compensate(a) => crate::compensate::compensate_cmd(&a),
        Command::Link(a) => crate::link::link_cmd(&a),
        Command::ServoBench(a) => crate::servo_bench::servo_bench_cmd(&a),
        Command::Settle(a) => crate::settle::settle_cmd(&a),
        Command::ServoTune(a) => crate::servo_tune::servo_tune_cmd(&a),
        Command::Learn(a) => crate::learn::learn_cmd(&a),
        Command::LearnBench(a) => crate::learn_bench::learn_bench_cmd(&a),
    }
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
        let help = long_help("simulate");
        for word in [
            "nac2024",
            "xy-stage",
            "staircase",
            "raster",
            "creep",
            "second-mode",
            "duration (s)",
        ] {
            assert!(help.contains(word), "help lacks {word}");
        }
    }

    /// `host-sim COMMAND --help` as printed.
    fn long_help(command: &str) -> String {
        Cli::command()
            .find_subcommand_mut(command)
            .unwrap()
            .render_long_help()
            .to_string()
    }

    /// Every command and subcommand, with its long help rendered as `--help` prints it.
    fn rendered_helps() -> Vec<(String, String, String)> {
        fn walk(cmd: &mut clap::Command, path: &str, out: &mut Vec<(String, String, String)>) {
            let names: Vec<String> = cmd
                .get_subcommands()
                .map(|c| c.get_name().to_string())
                .filter(|n| n != "help")
                .collect();
            for name in names {
                let sub = cmd.find_subcommand_mut(&name).unwrap();
                let about = sub.get_about().map(|a| a.to_string()).unwrap_or_default();
                let help = sub.render_long_help().to_string();
                let full = format!("{path} {name}");
                out.push((full.clone(), about, help));
                walk(sub, &full, out);
            }
        }
        let mut out = Vec::new();
        walk(&mut Cli::command(), "host-sim", &mut out);
        out
    }

    #[test]
    fn every_command_names_its_units_in_its_first_sentence() {
        const UNITS: [&str; 10] = [
            "(V)",
            "volts",
            "metres",
            "(m)",
            " in m",
            "(s)",
            "Hz",
            "% of stroke",
            "µm",
            "t_s",
        ];
        let mut commands = 0;
        for (name, about, _) in rendered_helps() {
            if name.matches(' ').count() != 1 {
                continue;
            }
            commands += 1;
            let first = about.split(". ").next().unwrap_or_default();
            assert!(
                UNITS.iter().any(|u| first.contains(u)),
                "`{name} --help` names no unit in its first sentence: {first}"
            );
        }
        assert!(commands >= 14, "{commands} commands");
    }

    #[test]
    fn units_in_every_help_are_written_one_way() {
        let mut offenders = Vec::new();
        for (name, _, help) in rendered_helps() {
            for line in help.lines() {
                let escaped = line.contains("\\[");
                let bracketed = [
                    "[Hz]", "[s]", "[V]", "[m]", "[°]", "[%]", "[V/s]", "[nm]", "[µm]",
                ]
                .iter()
                .any(|b| line.contains(b));
                if escaped || bracketed {
                    offenders.push(format!("{name}: {}", line.trim()));
                }
            }
        }
        assert!(
            offenders.is_empty(),
            "units are written (unit), never [unit] or \\[unit\\]:\n{}",
            offenders.join("\n")
        );
        fn every_signal(cmd: &clap::Command, path: &str, count: &mut usize) {
            for arg in cmd.get_arguments().filter(|a| a.get_id() == "signal") {
                *count += 1;
                let help = arg
                    .get_long_help()
                    .or(arg.get_help())
                    .map(|h| h.to_string())
                    .unwrap_or_default();
                assert!(
                    ["volts", "metres", "µm"].iter().any(|u| help.contains(u)),
                    "`{path} --signal` names no unit: {help}"
                );
            }
            for sub in cmd.get_subcommands() {
                every_signal(sub, &format!("{path} {}", sub.get_name()), count);
            }
        }
        let mut signals = 0;
        every_signal(&Cli::command(), "host-sim", &mut signals);
        assert!(signals >= 5, "{signals} --signal options");
        let help = long_help("simulate");
        assert!(help.contains("U is the signal's own unit"), "{help}");
    }

    #[test]
    fn demo_and_reproduce_help_document_their_options() {
        let help = long_help("demo");
        for word in [
            "--out",
            "--x-freq",
            "--y-freq",
            "--duration",
            "--low",
            "--high",
            "--rate",
            "--settle",
            "--format",
            "out/demo",
        ] {
            assert!(help.contains(word), "demo help lacks {word}");
        }
        let help = long_help("reproduce");
        for word in ["--out", "--format", "xy_stage", "nac2024", "stage"] {
            assert!(help.contains(word), "reproduce help lacks {word}");
        }
    }

    /// Every command with a plot `--format` writes the same formats without it (SVG and PNG), and
    /// says which in its help.
    #[test]
    fn every_plot_format_defaults_alike() {
        fn walk(cmd: &clap::Command, path: &str, out: &mut Vec<(String, String)>) {
            for arg in cmd.get_arguments().filter(|a| a.get_id() == "format") {
                let default: Vec<String> = arg
                    .get_default_values()
                    .iter()
                    .map(|v| v.to_string_lossy().into_owned())
                    .collect();
                out.push((path.to_string(), default.join(",")));
            }
            for sub in cmd.get_subcommands() {
                walk(sub, &format!("{path} {}", sub.get_name()), out);
            }
        }
        let mut formats = Vec::new();
        walk(&Cli::command(), "host-sim", &mut formats);
        let names: Vec<&str> = formats.iter().map(|(n, _)| n.as_str()).collect();
        for command in ["demo", "reproduce", "servo-bench", "learn-bench"] {
            assert!(
                names.contains(&format!("host-sim {command}").as_str()),
                "{names:?}"
            );
            assert!(
                long_help(command).contains("[default: both]"),
                "{command} --help does not state its --format default"
            );
        }
        assert!(
            formats.iter().all(|(_, d)| d == "both"),
            "--format defaults differ: {formats:?}"
        );
    }

    /// `compensate --reference` is read without `--signal` and written with it: its help says so.
    #[test]
    fn compensate_help_says_when_the_reference_is_written() {
        let help = long_help("compensate");
        // The option's own entry: after the usage line's mention, before `--signal`'s entry.
        let entry = help
            .rsplit("--reference <REFERENCE>")
            .next()
            .and_then(|h| h.split("--signal <SIGNAL>").next())
            .unwrap_or_default();
        let reference = entry.split_whitespace().collect::<Vec<_>>().join(" ");
        assert!(
            reference.contains("With `--signal`: where") && reference.contains("written"),
            "{reference}"
        );
    }

    #[test]
    fn demo_errors_name_the_option() {
        let cli = Cli::try_parse_from(["host-sim", "demo", "--x-freq", "0"]).unwrap();
        let e = run(cli).unwrap_err().to_string();
        assert!(e.starts_with("--x-freq"), "{e}");
        let cli =
            Cli::try_parse_from(["host-sim", "demo", "--low", "0.5", "--high", "0.2"]).unwrap();
        assert!(run(cli).unwrap_err().to_string().starts_with("--low"));
        let e = Cli::try_parse_from(["host-sim", "demo", "--rate", "fast"])
            .unwrap_err()
            .to_string();
        assert!(e.contains("--rate"), "{e}");
    }

    #[test]
    fn errors_name_the_argument_and_choices() {
        let scratch = tempfile::tempdir().unwrap();
        let out = scratch.path().join("refused.csv");
        let e = run(args("nac", "sine", &[], &out)).unwrap_err().to_string();
        assert!(e.starts_with("--plant") && e.contains("xy-stage"), "{e}");
        let e = run(args("stage", "sine:freq=fast", &[], &out))
            .unwrap_err()
            .to_string();
        assert!(e.starts_with("--signal") && e.contains("fast"), "{e}");
        let e = run(args("stage", "sine", &["creeep"], &out))
            .unwrap_err()
            .to_string();
        assert!(e.starts_with("--effect") && e.contains("drift"), "{e}");
        let e = run(args("stage", "sine", &["coupling"], &out))
            .unwrap_err()
            .to_string();
        assert!(e.contains("xy-stage only"), "{e}");
    }

    #[test]
    fn simulate_writes_csv_and_svg() {
        let scratch = tempfile::tempdir().unwrap();
        let dir = scratch.path();
        let out = dir.join("xy.csv");
        let mut cli = args(
            "xy-stage",
            "raster:x_high=50,y_high=20,line_freq=10,duration=0.2,rate=2000",
            &[],
            &out,
        );
        let Command::Simulate(a) = &mut cli.command else {
            unreachable!()
        };
        a.plot = Some(dir.join("xy.svg"));
        run(cli).unwrap();
        let t = crate::csv::read_csv(&out).unwrap();
        assert_eq!(t.names, ["t_s", "ux_V", "uy_V", "x_m", "y_m"]);
        assert_eq!(t.rows(), 400);
        let svg = std::fs::read_to_string(dir.join("xy.svg")).unwrap();
        assert!(svg.contains("<svg") && svg.contains("hysteresis loop"));
    }

    #[test]
    fn simulate_plots_png_and_refuses_other_extensions() {
        let scratch = tempfile::tempdir().unwrap();
        let dir = scratch.path();
        let out = dir.join("stage.csv");
        let cli_with_plot = |plot: &str| {
            let mut cli = args(
                "stage",
                "sine:amp=5,offset=5,freq=5,duration=0.2,rate=5000",
                &[],
                &out,
            );
            let Command::Simulate(a) = &mut cli.command else {
                unreachable!()
            };
            a.plot = Some(dir.join(plot));
            cli
        };
        run(cli_with_plot("stage.png")).unwrap();
        let png = std::fs::read(dir.join("stage.png")).unwrap();
        assert!(png.starts_with(b"\x89PNG\r\n\x1a\n"));
        let e = run(cli_with_plot("stage.pdf")).unwrap_err().to_string();
        assert!(e.starts_with("--plot") && e.contains(".pdf"), "{e}");
        assert!(!dir.join("stage.pdf").exists());
    }
}
