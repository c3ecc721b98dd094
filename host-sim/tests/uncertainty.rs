//! The uncertainty `identify` reports, checked against the truth: records of a known static
//! Bouc-Wen set simulated by piezo-reference's f64 law (not the core) with white sensor noise,
//! fitted for 50 noise seeds; the ±2σ intervals must cover the true k1, β, γ and n in 88–99 % of
//! the fits each (nominal 95.4 %), and must not with standard errors 0.3 times as large; the
//! prediction band must be within a factor 1.5 of the RMS error measured on a second input of the
//! same kind (another amplitude and frequency). The report and the text carry them, and `predict`
//! prints the band beside the RMS it measures.

use clap::Parser;
use host_sim::bouc_wen::BoucWen;
use host_sim::cli::{run, Cli};
use host_sim::identify::model::{Identified, ModelKind};
use host_sim::identify::{fit_uncertainty, identify, score, IdentifySettings, Record};
use rand_chacha::ChaCha8Rng;
use rand_core::{RngCore, SeedableRng};
use rayon::prelude::*;
use std::f64::consts::PI;
use std::path::PathBuf;

mod common;
use common::temp;

/// The true set: A = 1 (the fit's scale convention), state bound H = (1/(β + γ))^(1/n) = 20 V,
/// (β − γ)/(β + γ) = 0.5, n = 1.5; y = k1·u + k2·h + y0.
const N_TRUE: f64 = 1.5;
const K1: f64 = 1.0e-7;
const K2: f64 = -0.4e-7;
const Y0: f64 = 2.0e-7;
/// White sensor noise \[m\] (0.2 % of the 10 µm stroke).
const NOISE_M: f64 = 20e-9;
/// Samples per record.
const N: usize = 2000;
/// Sample period \[s\].
const TS: f64 = 1e-3;
/// Noise seeds.
const SEEDS: u64 = 50;

fn truth() -> BoucWen {
    let sum = 20f64.powf(-N_TRUE);
    BoucWen {
        a: 1.0,
        beta: 0.75 * sum,
        gamma: 0.25 * sum,
        n: N_TRUE,
    }
}

/// u = offset − amp·cos(2π f t), from rest at its first sample.
fn input(amp: f64, offset: f64, freq_hz: f64) -> Vec<f64> {
    (0..N)
        .map(|k| offset - amp * (2.0 * PI * freq_hz * k as f64 * TS).cos())
        .collect()
}

/// The noiseless output of the true set (the reference's f64 law, rate-independent jumps).
fn clean_output(u: &[f64]) -> Vec<f64> {
    let bw = truth();
    let mut h = 0.0;
    let mut prev = u[0];
    u.iter()
        .map(|&v| {
            h = bw.jump(h, prev, v);
            prev = v;
            K1 * v + K2 * h + Y0
        })
        .collect()
}

fn normal(rng: &mut ChaCha8Rng) -> f64 {
    let u1 = (rng.next_u64() >> 11) as f64 / (1u64 << 53) as f64;
    let u2 = (rng.next_u64() >> 11) as f64 / (1u64 << 53) as f64;
    (-2.0 * (1.0 - u1).ln()).sqrt() * (2.0 * PI * u2).cos()
}

fn record(u: &[f64], clean: &[f64], seed: u64) -> Record {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let y = clean
        .iter()
        .map(|c| c + NOISE_M * normal(&mut rng))
        .collect();
    let t = (0..u.len()).map(|k| k as f64 * TS).collect();
    Record::from_parts(format!("seed{seed}.csv").into(), t, u.to_vec(), y)
}

/// One fit: (fitted, standard error) of k1, β, γ, n; the band; the RMS error on the second input.
struct Fit {
    values: [f64; 4],
    errors: [f64; 4],
    band_m: f64,
    second_rms_m: f64,
}

fn fit(seed: u64, first: (&[f64], &[f64]), second: (&[f64], &[f64])) -> Fit {
    let settings = IdentifySettings::new(ModelKind::Symmetric);
    let rec = record(first.0, first.1, seed);
    let id = identify(&rec, &settings).unwrap();
    let u = fit_uncertainty(&id, &rec, &settings).unwrap();
    let Identified::Static { bouc_wen, map, .. } = id.set else {
        panic!("static set expected")
    };
    let se = |name: &str| {
        let i = u.parameters.iter().position(|p| p.name == name).unwrap();
        u.standard_errors[i]
    };
    let check = record(second.0, second.1, 1000 + seed);
    Fit {
        values: [
            f64::from(map.k1_m_per_v),
            f64::from(bouc_wen.beta),
            f64::from(bouc_wen.gamma),
            f64::from(bouc_wen.n),
        ],
        errors: [
            se("static_map.k1_m_per_v"),
            se("bouc_wen.beta"),
            se("bouc_wen.gamma"),
            se("bouc_wen.n"),
        ],
        band_m: u.prediction_band_rms_m,
        second_rms_m: score(&id.set, &check, 0).unwrap().rms,
    }
}

/// Share of the fits whose interval value ± 2·scale·σ holds the truth, per parameter.
fn coverage(fits: &[Fit], scale: f64) -> [f64; 4] {
    let bw = truth();
    let truth = [K1, bw.beta, bw.gamma, bw.n];
    std::array::from_fn(|i| {
        let hits = fits
            .iter()
            .filter(|f| (f.values[i] - truth[i]).abs() <= 2.0 * scale * f.errors[i])
            .count();
        hits as f64 / fits.len() as f64
    })
}

#[test]
fn two_sigma_intervals_cover_the_truth_and_the_band_predicts_a_new_input() {
    // Two and a half periods of a 0–100 V sine; the second input: 10–80 V, another frequency.
    let u1 = input(50.0, 50.0, 1.25);
    let u2 = input(35.0, 45.0, 1.7);
    let (y1, y2) = (clean_output(&u1), clean_output(&u2));
    let fits: Vec<Fit> = (0..SEEDS)
        .into_par_iter()
        .map(|s| fit(s, (&u1, &y1), (&u2, &y2)))
        .collect();
    let names = ["k1", "beta", "gamma", "n"];
    let covered = coverage(&fits, 1.0);
    let shrunk = coverage(&fits, 0.3);
    for i in 0..4 {
        let mean_se = fits.iter().map(|f| f.errors[i]).sum::<f64>() / fits.len() as f64;
        let values: Vec<f64> = fits.iter().map(|f| f.values[i]).collect();
        let mean = values.iter().sum::<f64>() / values.len() as f64;
        let spread = (values.iter().map(|v| (v - mean).powi(2)).sum::<f64>()
            / (values.len() - 1) as f64)
            .sqrt();
        println!(
            "{}: coverage {:.0} % (with 0.3 σ: {:.0} %), mean standard error {mean_se:.3e}, \
             spread of the estimates {spread:.3e}",
            names[i],
            100.0 * covered[i],
            100.0 * shrunk[i]
        );
    }
    for i in 0..4 {
        assert!(
            (0.88..=0.99).contains(&covered[i]),
            "{}: ±2σ covers the truth in {:.0} % of {SEEDS} fits",
            names[i],
            100.0 * covered[i]
        );
        // Standard errors 0.3 times as large must fail the same check.
        assert!(
            shrunk[i] < 0.88,
            "{}: ±0.6σ still covers the truth in {:.0} % of the fits",
            names[i],
            100.0 * shrunk[i]
        );
    }
    let ratios: Vec<f64> = fits.iter().map(|f| f.band_m / f.second_rms_m).collect();
    let (lo, hi) = ratios
        .iter()
        .fold((f64::INFINITY, 0.0f64), |(a, b), &r| (a.min(r), b.max(r)));
    println!("band / RMS on the second input: {lo:.3}–{hi:.3}");
    assert!(
        lo >= 1.0 / 1.5 && hi <= 1.5,
        "band / measured RMS on the second input spans {lo:.3}–{hi:.3}"
    );
}

fn write_csv(name: &str, r: &Record) -> PathBuf {
    let path = temp(name);
    let mut text = String::from("t_s,u_V,y_m\n");
    for k in 0..r.u.len() {
        text.push_str(&format!("{},{},{}\n", r.t_s[k], r.u[k], r.y_m[k]));
    }
    std::fs::write(&path, text).unwrap();
    path
}

fn cli(args: &[&str]) -> Result<String, String> {
    let mut v = vec!["host-sim"];
    v.extend_from_slice(args);
    run(Cli::try_parse_from(v).map_err(|e| e.to_string())?).map_err(|e| e.to_string())
}

fn json(path: &std::path::Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

#[test]
fn the_report_and_predict_carry_the_uncertainty() {
    let u1 = input(50.0, 50.0, 1.25);
    let u2 = input(35.0, 45.0, 1.7);
    let fitted = write_csv("fit.csv", &record(&u1, &clean_output(&u1), 1));
    let check = write_csv("check.csv", &record(&u2, &clean_output(&u2), 2));
    let (stage, report) = (temp("stage.toml"), temp("identify.json"));
    let text = cli(&[
        "identify",
        "--data",
        fitted.to_str().unwrap(),
        "--model",
        "symmetric",
        "--out",
        stage.to_str().unwrap(),
        "--report",
        report.to_str().unwrap(),
    ])
    .unwrap();
    assert!(
        text.contains("bouc_wen.n = ") && text.contains(" ± "),
        "{text}"
    );
    assert!(text.contains("prediction band: rms"), "{text}");
    let r = json(&report);
    // Standard errors nested as the parameters, every fitted one positive.
    for (group, key) in [
        ("bouc_wen", "beta"),
        ("bouc_wen", "gamma"),
        ("bouc_wen", "n"),
        ("static_map", "k1_m_per_v"),
        ("static_map", "k2_m_per_h"),
        ("static_map", "offset_m"),
    ] {
        assert!(
            r["params"][group][key].is_number(),
            "params lack {group}.{key}"
        );
        let se = r["uncertainty"][group][key].as_f64().unwrap_or(f64::NAN);
        assert!(se > 0.0 && se.is_finite(), "{group}.{key}: {se}");
    }
    // A is the scale convention, not fitted.
    assert!(r["uncertainty"]["bouc_wen"].get("a").is_none());
    let names = r["correlation"]["names"].as_array().unwrap();
    let matrix = r["correlation"]["matrix"].as_array().unwrap();
    assert_eq!(names.len(), 6);
    for (i, row) in matrix.iter().enumerate() {
        for (j, v) in row.as_array().unwrap().iter().enumerate() {
            let (v, t) = (v.as_f64().unwrap(), matrix[j][i].as_f64().unwrap());
            assert!((v - t).abs() < 1e-12 && v.abs() <= 1.0);
            if i == j {
                assert!((v - 1.0).abs() < 1e-12);
            }
        }
    }
    let band = r["prediction_band_rms_m"].as_f64().unwrap();
    assert!(band > 0.8 * NOISE_M && band < 1.5 * NOISE_M, "band {band}");
    // predict prints the band beside the RMS it measures, and reports both.
    let predicted = temp("predict.json");
    let line = cli(&[
        "predict",
        "--params",
        stage.to_str().unwrap(),
        "--data",
        check.to_str().unwrap(),
        "--fit-report",
        report.to_str().unwrap(),
        "--report",
        predicted.to_str().unwrap(),
    ])
    .unwrap();
    assert!(line.contains("prediction band of the fit: rms"), "{line}");
    let p = json(&predicted);
    assert_eq!(p["prediction_band_rms_m"].as_f64(), Some(band));
    let ratio = p["axes"][0]["rms_over_band"].as_f64().unwrap();
    assert!(
        (1.0 / 1.5..=1.5).contains(&ratio),
        "measured / band {ratio}"
    );
    // A file that is not such a report is named, with the key it lacks or where it is broken.
    let other = temp("other.json");
    std::fs::write(&other, "{\"model\": \"symmetric\"}").unwrap();
    let broken = temp("broken.json");
    std::fs::write(&broken, "{\"model\":\n  symmetric}").unwrap();
    for (file, says) in [
        (&other, "no prediction_band_rms_m"),
        (&broken, "line 2 column 3"),
    ] {
        let e = cli(&[
            "predict",
            "--params",
            stage.to_str().unwrap(),
            "--data",
            check.to_str().unwrap(),
            "--fit-report",
            file.to_str().unwrap(),
            "--report",
            predicted.to_str().unwrap(),
        ])
        .unwrap_err();
        assert!(
            e.contains(&file.display().to_string()) && e.contains(says),
            "{e}"
        );
    }
}

#[test]
fn the_dynamic_model_reports_the_uncertainty_of_its_eight_parameters() {
    let (data, stage, report) = (temp("nac.csv"), temp("nac.toml"), temp("nac.json"));
    cli(&[
        "simulate",
        "--plant",
        "nac2024",
        "--signal",
        "sine:amp=4.869,offset=4.869,freq=10000,phase_deg=-90,duration=3e-4,rate=2560000",
        "--effect",
        "noise:rms_m=1e-11,seed=1",
        "--out",
        data.to_str().unwrap(),
    ])
    .unwrap();
    cli(&[
        "identify",
        "--data",
        data.to_str().unwrap(),
        "--model",
        "dynamic",
        "--allow-refused",
        "--out",
        stage.to_str().unwrap(),
        "--report",
        report.to_str().unwrap(),
    ])
    .unwrap();
    let r = json(&report);
    let names = r["correlation"]["names"].as_array().unwrap();
    assert_eq!(names.len(), 8, "{names:?}");
    for name in names {
        let (group, key) = name.as_str().unwrap().split_once('.').unwrap();
        assert!(r["params"][group][key].is_number(), "params lack {name}");
        let se = r["uncertainty"][group][key].as_f64().unwrap_or(f64::NAN);
        assert!(se > 0.0 && se.is_finite(), "{name}: {se}");
    }
    let band = r["prediction_band_rms_m"].as_f64().unwrap();
    let rms = r["fit"]["rms"].as_f64().unwrap();
    assert!(
        band >= rms && band < 1.5 * rms,
        "band {band}, fit rms {rms}"
    );
}
