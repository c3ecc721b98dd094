//! The house style: figure sizes, fonts, a colour per role, tick labels and unit labels.
//!
//! Sizes are in SVG pixels. Figures are drawn at twice the size they are meant to be viewed at, so the
//! integer pixel coordinates of the SVG backend still place lines to half a pixel, and a PNG rendered
//! one to one is sharp on a high-density screen and in a slide.

use plotters::coord::ranged1d::Ranged;
use plotters::coord::types::RangedCoordf64;
use plotters::style::RGBColor;

/// Width of a panel (axes, labels and data area; the legend is added) in a figure of one column, px.
pub const PANEL_WIDTH: u32 = 1500;
/// Width of a panel in a figure of several columns, px.
pub const GRID_PANEL_WIDTH: u32 = 1000;
/// Height of one panel, caption included, px.
pub const PANEL_HEIGHT: u32 = 560;
/// Panel caption, px.
pub const TITLE_FONT: u32 = 30;
/// Axis descriptions, px.
pub const AXIS_FONT: u32 = 26;
/// Tick labels, px.
pub const TICK_FONT: u32 = 24;
/// Legend entries, px.
pub const LEGEND_FONT: u32 = 24;
/// Width of a line series, px.
pub const LINE_WIDTH: u32 = 3;
/// Width of the line joining markers and of reference lines, px.
pub const THIN_WIDTH: u32 = 2;
/// Line width of a measured series \[px\]: a broad band under the thinner lines drawn over it, so
/// that a model lying on the measurement shows as a line inside the band, not hiding it.
pub const MEASURED_WIDTH: u32 = 9;
/// Marker radius, px.
pub const MARKER_RADIUS: u32 = 6;
/// Dash and gap of dashed lines, px.
pub const DASH: (u32, u32) = (14, 8);
/// Tick labels on a linear x axis, at most.
pub const X_TICKS: usize = 9;
/// Tick labels on a linear y axis, at most.
pub const Y_TICKS: usize = 7;
/// Legend sample length, px.
pub const LEGEND_SAMPLE: u32 = 54;
/// Space around the legend and between its entries, px.
pub const LEGEND_GAP: u32 = 16;
/// Narrowest and widest legend column, px.
pub const LEGEND_WIDTH: (u32, u32) = (180, 560);

/// Width of a panel in a figure of `columns` columns, px.
pub fn panel_width(columns: usize) -> u32 {
    if columns > 1 {
        GRID_PANEL_WIDTH
    } else {
        PANEL_WIDTH
    }
}

/// Grid lines.
pub const GRID: RGBColor = RGBColor(222, 222, 222);
/// Axes, frame and text.
pub const INK: RGBColor = RGBColor(30, 30, 30);
/// Horizontal reference lines (noise floor, limits).
pub const REFERENCE_LINE: RGBColor = RGBColor(90, 90, 90);
/// Fill of a marked window (validation window, scored window).
pub const WINDOW_FILL: RGBColor = RGBColor(0, 114, 178);
/// Fill of an excluded interval (a transient outside the scored window).
pub const EXCLUDED_FILL: RGBColor = RGBColor(120, 120, 120);

/// What a curve shows; each role has its colour in every figure.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Role {
    /// A measured (or simulated plant) output.
    Measured,
    /// A model's prediction.
    Model,
    /// The reference (set point) a controller tracks; drawn dashed, on top of the other curves.
    Reference,
    /// A residual (measured − model).
    Residual,
    /// Linear (affine) feed-forward or open-loop drive: the uncompensated stage.
    OpenLoop,
    /// Model-based feed-forward compensation.
    Feedforward,
    /// Feedback control alone.
    Feedback,
    /// Feed-forward compensation with feedback.
    FeedforwardFeedback,
    /// Any other curve: the n-th colour of a palette that avoids the role colours.
    Other(usize),
}

/// The Okabe–Ito colours (distinguishable with the common colour-vision deficiencies) and two more.
const OTHER: [RGBColor; 6] = [
    RGBColor(0, 114, 178),
    RGBColor(213, 94, 0),
    RGBColor(0, 158, 115),
    RGBColor(204, 121, 167),
    RGBColor(230, 159, 0),
    RGBColor(86, 180, 233),
];

impl Role {
    /// The colour of this role.
    pub fn colour(self) -> RGBColor {
        match self {
            Role::Measured => RGBColor(175, 175, 175),
            Role::Model => RGBColor(213, 94, 0),
            Role::Reference => RGBColor(0, 0, 0),
            Role::Residual => RGBColor(117, 112, 179),
            Role::OpenLoop => RGBColor(230, 159, 0),
            Role::Feedforward => RGBColor(0, 114, 178),
            Role::Feedback => RGBColor(0, 158, 115),
            Role::FeedforwardFeedback => RGBColor(204, 121, 167),
            Role::Other(i) => OTHER[i % OTHER.len()],
        }
    }
}

/// The axis label with its unit in µm: `[um]` → `[µm]` (also in `[um/V]`-like units).
pub fn unit_label(label: &str) -> String {
    label.replace("[um]", "[µm]").replace("[um/", "[µm/")
}

/// Tick labels of a linear axis over `range`: as many decimals as the tick step needs, a true minus
/// sign, and never "−0.0".
pub fn linear_tick_format(range: (f64, f64), max_ticks: usize) -> impl Fn(&f64) -> String {
    let ticks = RangedCoordf64::from(range.0..range.1).key_points(max_ticks);
    let step = ticks
        .windows(2)
        .map(|w| (w[1] - w[0]).abs())
        .fold(f64::INFINITY, f64::min);
    let decimals = if step.is_finite() && step > 0.0 {
        (-(step.log10() + 1e-9).floor()).clamp(0.0, 12.0) as usize
    } else {
        3
    };
    move |v: &f64| number(*v, decimals)
}

/// Tick labels of a logarithmic axis: 0.01, 0.1, 1, 10, 100, … and 1e-5, 1e6 outside 1e-3 … 1e5.
pub fn log_tick_format(v: &f64) -> String {
    let v = *v;
    if !(v > 0.0) {
        return number(v, 0);
    }
    let exponent = v.log10().round();
    let decade = (v.log10() - exponent).abs() < 1e-9;
    if (-3.0..=5.0).contains(&exponent) {
        let decimals = (-v.log10().floor()).max(0.0) as usize;
        number(v, decimals)
    } else if decade {
        minus(format!("1e{exponent}"))
    } else {
        minus(format!("{v:.0e}"))
    }
}

/// `v` with `decimals` decimals, "−" for negative numbers and no negative zero.
pub fn number(v: f64, decimals: usize) -> String {
    let s = format!("{v:.decimals$}");
    if s.starts_with('-') && s[1..].chars().all(|c| c == '0' || c == '.') {
        return s[1..].to_string();
    }
    minus(s)
}

fn minus(s: String) -> String {
    s.replace('-', "\u{2212}")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ticks_have_no_negative_zero_and_enough_decimals() {
        assert_eq!(number(-0.0001, 1), "0.0");
        assert_eq!(number(-0.25, 2), "\u{2212}0.25");
        let f = linear_tick_format((-0.3, 0.3), 7);
        assert_eq!(f(&-0.0), "0.0");
        assert_eq!(f(&0.1), "0.1");
        let f = linear_tick_format((0.0, 120.0), 9);
        assert_eq!(f(&20.0), "20");
    }

    #[test]
    fn log_ticks_read_as_numbers() {
        assert_eq!(log_tick_format(&0.01), "0.01");
        assert_eq!(log_tick_format(&1000.0), "1000");
        assert_eq!(log_tick_format(&1e-6), "1e\u{2212}6");
        assert_eq!(log_tick_format(&1e7), "1e7");
    }

    #[test]
    fn micrometres_are_spelled_with_mu() {
        assert_eq!(unit_label("residual [um]"), "residual [µm]");
        assert_eq!(unit_label("gain [um/V]"), "gain [µm/V]");
    }
}
