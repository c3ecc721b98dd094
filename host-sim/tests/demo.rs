//! The demo and reproduce commands, shortened.

use host_sim::demo::{run_demo, DemoSettings};

/// The demo's story, shortened: on the XY stage with undeclared creep, close-loop names creep on both
/// axes, the identified base model beats the best linear feed-forward, and adding the effect cuts the
/// compensated error again.
#[test]
fn shortened_demo_finds_creep_and_compensates_it() {
    let settings = DemoSettings {
        x_frequency_hz: 4.0,
        y_frequency_hz: 2.0,
        duration_s: 1.0,
        identify_s: 2.0,
        ..Default::default()
    };
    let r = run_demo(&settings, &mut |_| {}).unwrap();
    for axis in 0..2 {
        let (l, b, c) = (
            r.linear.errors[axis].rms_m,
            r.base.errors[axis].rms_m,
            r.closed.errors[axis].rms_m,
        );
        let added: Vec<&str> = r.close_loop.axes[axis]
            .model
            .added
            .iter()
            .map(|e| e.name())
            .collect();
        assert_eq!(added.first(), Some(&"creep"), "axis {axis}: {added:?}");
        assert!(
            b < 0.5 * l,
            "axis {axis}: base {b:e} vs uncompensated {l:e}"
        );
        assert!(c < 0.5 * b, "axis {axis}: with effects {c:e} vs base {b:e}");
        // The uncompensated error is hysteresis-sized (µm), not a gain or offset blunder.
        assert!(l > 0.5e-6 && l < 5e-6, "axis {axis}: uncompensated {l:e}");
    }
    let scratch = tempfile::tempdir().unwrap();
    let dir = scratch.path();
    let files = r.write(dir, &["svg", "png"]).unwrap();
    assert_eq!(files.len(), 9);
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("summary.json")).unwrap()).unwrap();
    assert!(
        json["x"]["compensated_with_effects"]["rms_um"]
            .as_f64()
            .unwrap()
            > 0.0
    );
    let png = std::fs::read(dir.join("error.png")).unwrap();
    assert_eq!(&png[1..4], b"PNG");
}

#[test]
fn reproduce_writes_every_figure_with_the_paper_value() {
    let report = host_sim::reproduce::run_reproduce(&mut |_| {}).unwrap();
    let j = host_sim::to_json(&report.report()).unwrap();
    for key in [
        "loop_opening_x_um_120V",
        "loop_opening_y_um_120V",
        "loop_opening_x_um_12V",
        "loop_opening_y_um_12V",
        "max_displacement_um",
    ] {
        let v = j["xy_stage"][key]["value"].as_f64().unwrap();
        let p = j["xy_stage"][key]["paper"].as_f64().unwrap();
        assert!((v - p).abs() < 0.1 * p, "{key}: {v} vs paper {p}");
    }
    let rows = j["nac2024"]["rows"].as_array().unwrap();
    assert_eq!(rows.len(), 11);
    for r in rows {
        // The core against the published plant agrees closely; the perturbed plant costs accuracy.
        assert!(r["baseline_r2"].as_f64().unwrap() > 0.999);
        assert!(r["r2"].as_f64().unwrap() > 0.9);
    }
    assert!(rows[0]["r2"].as_f64().unwrap() < rows[0]["baseline_r2"].as_f64().unwrap());
    let s = &j["stage"]["models_vs_plant_case_III"];
    let afv = |k: &str| s[k]["afv_um"].as_f64().unwrap();
    assert!(afv("III_delta_phi") < afv("I_standard"));
    let scratch = tempfile::tempdir().unwrap();
    let files = report.write(scratch.path(), &["svg"]).unwrap();
    assert_eq!(files.len(), 4);
}
