//! Every kind of figure rendered to PNG: it decodes, and it is not blank (a good share of pixels are
//! not background, and there are several colours).

use host_sim::plot::{
    plot_grid, plot_panels, Chart, Interval, Legend, Panel, ReferenceLine, Role, Series,
};
use resvg::tiny_skia::Pixmap;
use std::f64::consts::PI;
use std::path::{Path, PathBuf};

/// A directory of its own under the system temporary directory, removed when dropped; with
/// `HOST_SIM_PLOT_DIR` set, that directory instead, kept for a look at the figures.
struct TempDir(PathBuf, bool);

impl TempDir {
    fn new(name: &str) -> Self {
        if let Some(keep) = std::env::var_os("HOST_SIM_PLOT_DIR") {
            std::fs::create_dir_all(&keep).unwrap();
            return Self(PathBuf::from(keep), false);
        }
        let dir = std::env::temp_dir().join(format!(
            "host-sim-plots-{name}-{}-{:?}",
            std::process::id(),
            std::time::SystemTime::now()
        ));
        std::fs::create_dir_all(&dir).unwrap();
        Self(dir, true)
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        if self.1 {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }
}

/// Decodes the PNG at `path` and checks that it shows something.
fn check_png(path: &Path) {
    let bytes = std::fs::read(path).unwrap();
    assert!(bytes.starts_with(b"\x89PNG\r\n\x1a\n"), "not a PNG");
    let pixmap = Pixmap::decode_png(&bytes).unwrap();
    assert!(pixmap.width() >= 1000 && pixmap.height() >= 400);
    let pixels = pixmap.pixels();
    let inked = pixels
        .iter()
        .filter(|p| (p.red(), p.green(), p.blue()) != (255, 255, 255))
        .count();
    let share = inked as f64 / pixels.len() as f64;
    assert!(
        share > 0.02,
        "{}: only {:.2} % drawn",
        path.display(),
        share * 100.0
    );
    let mut colours: Vec<(u8, u8, u8)> = pixels
        .iter()
        .map(|p| (p.red() & 0xf0, p.green() & 0xf0, p.blue() & 0xf0))
        .collect();
    colours.sort_unstable();
    colours.dedup();
    assert!(
        colours.len() >= 8,
        "{}: {} colours",
        path.display(),
        colours.len()
    );
}

fn sine(f: f64, a: f64, n: usize) -> Vec<(f64, f64)> {
    (0..n)
        .map(|k| {
            let t = k as f64 / 1000.0;
            (t, a * (2.0 * PI * f * t).sin())
        })
        .collect()
}

#[test]
fn time_series_with_a_reference_on_top() {
    let dir = TempDir::new("time");
    let path = dir.0.join("time.png");
    let measured: Vec<(f64, f64)> = sine(2.0, 10.0, 2000)
        .into_iter()
        .map(|(t, y)| (t, y + 0.3 * (t * 977.0).sin()))
        .collect();
    let panel = Panel::new(
        "tracking",
        "t [s]",
        "x [um]",
        vec![
            Series::line("reference", sine(2.0, 10.0, 2000), 4000).role(Role::Reference),
            Series::line("feed-forward", measured, 4000).role(Role::Feedforward),
        ],
    );
    plot_panels(&path, &[panel]).unwrap();
    check_png(&path);
}

#[test]
fn hysteresis_loop() {
    let dir = TempDir::new("loop");
    let path = dir.0.join("loop.png");
    let points: Vec<(f64, f64)> = (0..4000)
        .map(|k| {
            let p = 2.0 * PI * k as f64 / 1000.0;
            let u = 60.0 - 60.0 * p.cos();
            (u, 0.1 * u + 1.5 * p.sin())
        })
        .collect();
    let model: Vec<(f64, f64)> = points.iter().map(|&(u, y)| (u, y * 0.97)).collect();
    let panels = [
        Panel::new(
            "loop",
            "u [V]",
            "y [µm]",
            vec![
                Series::line("measured", points, 4000).role(Role::Measured),
                Series::line("model", model, 4000).role(Role::Model),
            ],
        ),
        Panel::new(
            "error",
            "u [V]",
            "error [µm]",
            vec![Series::line("residual", sine(3.0, 0.02, 4000), 4000).role(Role::Residual)],
        ),
    ];
    plot_grid(&path, &panels, 2).unwrap();
    check_png(&path);
}

#[test]
fn log_log_spectrum_with_a_noise_floor() {
    let dir = TempDir::new("spectrum");
    let path = dir.0.join("spectrum.png");
    let spectrum: Vec<(f64, f64)> = (0..5000)
        .map(|k| {
            let f = 0.2 * k as f64;
            (
                f,
                1.0 / (1.0 + f * f / 100.0) + 1e-3 * (1.0 + (k as f64).sin().abs()),
            )
        })
        .collect();
    let chart: Chart = Panel::new(
        "residual amplitude spectrum",
        "f [Hz]",
        "amplitude [µm]",
        vec![Series::line("residual", spectrum, 1000).role(Role::Residual)],
    )
    .log_log()
    .reference_line(ReferenceLine::new("noise floor", 2e-3));
    plot_panels(&path, &[chart]).unwrap();
    check_png(&path);
}

#[test]
fn marked_window_and_excluded_transient_with_a_clipped_spike() {
    let dir = TempDir::new("window");
    let path = dir.0.join("window.png");
    let mut error = sine(5.0, 0.05, 2000);
    error[0].1 = -6.0;
    let panels = [
        Panel::new(
            "compensated error",
            "t [s]",
            "error [µm]",
            vec![
                Series::line("feed-forward", error.clone(), 4000).role(Role::Feedforward),
                Series::line("feed-forward + feedback", error, 4000)
                    .role(Role::FeedforwardFeedback),
            ],
        )
        .y_range(-0.08, 0.08)
        .interval(Interval::excluded("transient (not scored)", 0.0, 0.05))
        .interval(Interval::window("validation window", 1.0, 2.0))
        .legend(Legend::Below),
        Panel::new(
            "open loop",
            "t [s]",
            "error [µm]",
            vec![Series::line("open loop", sine(1.0, 2.0, 2000), 4000).role(Role::OpenLoop)],
        )
        .into(),
    ];
    plot_panels(&path, &panels).unwrap();
    check_png(&path);
}

#[test]
fn markers_and_svg_of_the_same_figure() {
    let dir = TempDir::new("markers");
    let staircase: Vec<(f64, f64)> = (0..=24i32)
        .map(|k| {
            let u = 10.0 * (12 - (12 - k).abs()) as f64;
            (u, 0.15 * u + if k > 12 { 1.0 } else { 0.0 })
        })
        .collect();
    let panel = Panel::new(
        "settled loop",
        "input [V]",
        "platform [µm]",
        vec![
            Series::markers("x", staircase.clone()),
            Series::markers("y", staircase.iter().map(|&(u, y)| (u, 0.9 * y)).collect()),
        ],
    );
    let png = dir.0.join("markers.png");
    let svg = dir.0.join("markers.svg");
    plot_panels(&png, std::slice::from_ref(&panel)).unwrap();
    plot_panels(&svg, &[panel]).unwrap();
    check_png(&png);
    let text = std::fs::read_to_string(&svg).unwrap();
    assert!(text.starts_with("<svg") && text.contains("settled loop"));
}

#[test]
fn unknown_extensions_are_refused() {
    let dir = TempDir::new("refused");
    let path = dir.0.join("figure.pdf");
    let panel = Panel::new(
        "p",
        "x",
        "y",
        vec![Series::line("s", sine(1.0, 1.0, 10), 10)],
    );
    let e = plot_panels(&path, &[panel]).unwrap_err();
    assert!(e.to_string().contains(".svg or .png"), "{e}");
    assert!(!path.exists());
}
