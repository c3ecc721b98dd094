//! The one-line text form of a sample frame: what the firmware images print (QEMU over
//! semihosting, the board over defmt) and what `host-sim capture` reads back.
//!
//! ```text
//! frame 2000: x ref 0.000018998257 m cmd 58.12863 V sensor 0.000018887498 m | y ref 0.000004001112 m cmd 1.7004242 V sensor 0.0000040718746 m
//! ```
//!
//! [`Frame`]'s `Display` writes it and its `FromStr` reads it (the text carries the sequence
//! number and per axis reference, command and sensor; a frame read from text has `trial` and
//! `flags` 0). Values are f32 printed by
//! `Display` (shortest string that reads back to the same value, no exponent), so
//! `Display` → `FromStr` gives the same bits for every value except a NaN's payload (NaN prints
//! `NaN`, which reads back as NaN). The reader is more lenient than the writer: any run of
//! whitespace separates the words, a number may use an exponent (`1.9e-5`, as defmt prints), and
//! after the y axis a further `| …` field is ignored (room for a log's own annotations).
//! [`find_frame`] locates a frame after a prefix such as a defmt timestamp and level.
//! `host-sim`'s capture tests hold it as QEMU prints it and as probe-rs prints a defmt log.

use crate::Frame;
use core::fmt;
use core::str::FromStr;

/// The word that starts a frame.
pub const FRAME_PREFIX: &str = "frame ";

/// Axis names, in the order of [`Frame`]'s arrays.
pub const AXES: [&str; 2] = ["x", "y"];

/// Field names per axis: reference, command, sensor.
pub const FIELDS: [[&str; 3]; 2] = [
    ["x ref", "x cmd", "x sensor"],
    ["y ref", "y cmd", "y sensor"],
];

/// The text form of the module doc.
impl fmt::Display for Frame {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let (r, u, y) = (self.reference_m, self.commanded_v, self.sensor_m);
        write!(
            f,
            "frame {}: x ref {} m cmd {} V sensor {} m | y ref {} m cmd {} V sensor {} m",
            self.sequence, r[0], u[0], y[0], r[1], u[1], y[1]
        )
    }
}

/// What is wrong with a frame's text.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FrameTextErrorKind {
    /// The text does not start with `frame `.
    NotAFrame,
    /// No `:` after the sequence number.
    NoColon,
    /// The sequence number is not a u32.
    Sequence,
    /// An axis is missing (`x` or `y`).
    AxisMissing(&'static str),
    /// An axis's words are not `<axis> ref <m> m cmd <V> V sensor <m> m`.
    AxisLayout(&'static str),
    /// A value is not a number (one of [`FIELDS`]).
    Number(&'static str),
}

/// A frame's text that does not parse: what is wrong, and where (`start..end`, byte offsets into
/// the text given to `FromStr`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FrameTextError {
    /// What is wrong.
    pub kind: FrameTextErrorKind,
    /// Start of the offending part.
    pub start: usize,
    /// End of the offending part.
    pub end: usize,
}

impl FrameTextError {
    /// The offending part of `text` (the text that was parsed).
    pub fn found<'a>(&self, text: &'a str) -> &'a str {
        text.get(self.start..self.end).unwrap_or("")
    }

    /// The message with the offending part of `text` quoted.
    pub fn in_text<'a>(&'a self, text: &'a str) -> impl fmt::Display + 'a {
        InText { error: self, text }
    }
}

struct InText<'a> {
    error: &'a FrameTextError,
    text: &'a str,
}

impl fmt::Display for InText<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let found = self.error.found(self.text);
        match self.error.kind {
            FrameTextErrorKind::NotAFrame => write!(f, "does not start with `frame `"),
            FrameTextErrorKind::NoColon => f.write_str("no `:` after the sequence number"),
            FrameTextErrorKind::Sequence => {
                write!(f, "sequence number: `{found}` is not a number")
            }
            FrameTextErrorKind::AxisMissing(axis) => write!(f, "{axis} axis missing"),
            FrameTextErrorKind::AxisLayout(axis) => write!(
                f,
                "{axis} axis: expected `{axis} ref <m> m cmd <V> V sensor <m> m`, found `{found}`"
            ),
            FrameTextErrorKind::Number(field) => write!(f, "{field}: `{found}` is not a number"),
        }
    }
}

impl fmt::Display for FrameTextError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.kind {
            FrameTextErrorKind::NotAFrame => f.write_str("does not start with `frame `"),
            FrameTextErrorKind::NoColon => f.write_str("no `:` after the sequence number"),
            FrameTextErrorKind::Sequence => f.write_str("sequence number is not a number"),
            FrameTextErrorKind::AxisMissing(axis) => write!(f, "{axis} axis missing"),
            FrameTextErrorKind::AxisLayout(axis) => write!(
                f,
                "{axis} axis: expected `{axis} ref <m> m cmd <V> V sensor <m> m`"
            ),
            FrameTextErrorKind::Number(field) => write!(f, "{field}: not a number"),
        }
    }
}

/// Byte offset of `part` (a sub-slice of `whole`) in `whole`.
fn offset(whole: &str, part: &str) -> usize {
    (part.as_ptr() as usize).saturating_sub(whole.as_ptr() as usize)
}

/// Reads the text form of the module doc (`trial` and `flags` 0).
impl FromStr for Frame {
    type Err = FrameTextError;

    fn from_str(text: &str) -> Result<Self, FrameTextError> {
        let err = |kind, part: &str| {
            let start = offset(text, part);
            FrameTextError {
                kind,
                start,
                end: start + part.len(),
            }
        };
        let rest = text
            .strip_prefix(FRAME_PREFIX)
            .ok_or_else(|| err(FrameTextErrorKind::NotAFrame, &text[..0]))?;
        let (seq, rest) = rest
            .split_once(':')
            .ok_or_else(|| err(FrameTextErrorKind::NoColon, rest))?;
        let sequence: u32 = seq
            .parse()
            .map_err(|_| err(FrameTextErrorKind::Sequence, seq))?;
        let mut halves = rest.splitn(3, '|');
        let mut axes = [[0.0f32; 3]; 2];
        for (i, name) in AXES.into_iter().enumerate() {
            let half = halves
                .next()
                .ok_or_else(|| err(FrameTextErrorKind::AxisMissing(name), &text[text.len()..]))?;
            let layout = [name, "ref", "", "m", "cmd", "", "V", "sensor", "", "m"];
            let mut words = half.split_whitespace();
            let mut values = [""; 3];
            let mut n = 0;
            for expected in layout {
                match words.next() {
                    Some(w) if expected.is_empty() => {
                        values[n] = w;
                        n += 1;
                    }
                    Some(w) if w == expected => {}
                    _ => return Err(err(FrameTextErrorKind::AxisLayout(name), half.trim())),
                }
            }
            if words.next().is_some() {
                return Err(err(FrameTextErrorKind::AxisLayout(name), half.trim()));
            }
            for (c, w) in values.into_iter().enumerate() {
                axes[i][c] = w
                    .parse()
                    .map_err(|_| err(FrameTextErrorKind::Number(FIELDS[i][c]), w))?;
            }
        }
        let [x, y] = axes;
        Ok(Self {
            sequence,
            reference_m: [x[0], y[0]],
            commanded_v: [x[1], y[1]],
            sensor_m: [x[2], y[2]],
            trial: 0,
            flags: 0,
        })
    }
}

/// Where a frame (`frame <digits>:`) starts in a log line, if it holds one: the text from there
/// on is what [`Frame`]'s `FromStr` reads.
pub fn find_frame(line: &str) -> Option<usize> {
    let mut from = 0;
    while let Some(i) = line[from..].find(FRAME_PREFIX) {
        let at = from + i;
        let rest = &line[at + FRAME_PREFIX.len()..];
        let digits = rest.bytes().take_while(u8::is_ascii_digit).count();
        if digits > 0 && rest[digits..].starts_with(':') {
            return Some(at);
        }
        from = at + FRAME_PREFIX.len();
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame() -> Frame {
        Frame {
            sequence: 2000,
            reference_m: [1.5e-5, -1.5e-5],
            commanded_v: [3e-5, 3.0],
            sensor_m: [f32::NAN, 1e-6],
            trial: 7,
            flags: Frame::OUTSIDE_Y,
        }
    }

    /// x then y, `[reference_m, commanded_v, sensor_m]`.
    fn axes(f: &Frame) -> [[f32; 3]; 2] {
        [0, 1].map(|i| [f.reference_m[i], f.commanded_v[i], f.sensor_m[i]])
    }

    #[test]
    fn display_prints_the_documented_line() {
        assert_eq!(
            frame().to_string(),
            "frame 2000: x ref 0.000015 m cmd 0.00003 V sensor NaN m | y ref -0.000015 m cmd 3 V sensor 0.000001 m"
        );
    }

    #[test]
    fn display_then_parse_gives_the_same_bits() {
        let values = [
            0.0,
            -0.0,
            f32::MIN_POSITIVE,
            f32::from_bits(1),
            f32::MAX,
            f32::MIN,
            1.9094246e-5,
            core::f32::consts::PI,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
        ];
        for (k, &v) in values.iter().enumerate() {
            let f = Frame {
                sequence: u32::MAX - k as u32,
                reference_m: [v, 1.0 / v],
                commanded_v: [-v, v],
                sensor_m: [v * 0.5, 3.0],
                ..Frame::default()
            };
            let back: Frame = f.to_string().parse().unwrap();
            assert_eq!(back.sequence, f.sequence);
            for (a, b) in axes(&f).iter().flatten().zip(axes(&back).iter().flatten()) {
                assert!(
                    a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan()),
                    "{a} -> {b}"
                );
            }
        }
    }

    #[test]
    fn reads_defmt_exponents_extra_space_and_a_trailing_field() {
        let f: Frame = "frame 7:  x ref 1.9094246e-5 m cmd 20 V sensor 2.5e-6 m | y ref 0 m cmd 1 V sensor 0 m | wire [00]"
            .parse()
            .unwrap();
        assert_eq!(f.sequence, 7);
        assert_eq!(axes(&f), [[1.9094246e-5, 20.0, 2.5e-6], [0.0, 1.0, 0.0]]);
        assert_eq!((f.trial, f.flags), (0, 0));
    }

    #[test]
    fn errors_point_at_the_offending_text() {
        let bad = "frame 3: x ref 0.0x1 m cmd 40 V sensor 0 m | y ref 0 m cmd 1 V sensor 0 m";
        let e = bad.parse::<Frame>().unwrap_err();
        assert_eq!(e.kind, FrameTextErrorKind::Number("x ref"));
        assert_eq!(e.found(bad), "0.0x1");
        assert_eq!(e.in_text(bad).to_string(), "x ref: `0.0x1` is not a number");
        let short = "frame 3: x ref 0 m cmd 40 V sensor 0 m";
        let e = short.parse::<Frame>().unwrap_err();
        assert_eq!(e.kind, FrameTextErrorKind::AxisMissing("y"));
        let layout = "frame 3: x ref 0 m cmd 40 mV sensor 0 m | y ref 0 m cmd 1 V sensor 0 m";
        let e = layout.parse::<Frame>().unwrap_err();
        assert_eq!(e.kind, FrameTextErrorKind::AxisLayout("x"));
        assert_eq!(e.found(layout), "x ref 0 m cmd 40 mV sensor 0 m");
        let seq = "frame 99999999999: x ref 0 m cmd 1 V sensor 0 m | y ref 0 m cmd 1 V sensor 0 m";
        let e = seq.parse::<Frame>().unwrap_err();
        assert_eq!(e.kind, FrameTextErrorKind::Sequence);
        assert_eq!(e.found(seq), "99999999999");
    }

    #[test]
    fn finds_a_frame_after_a_prefix() {
        assert_eq!(find_frame("0.008 INFO  frame 12: x"), Some(12));
        assert_eq!(find_frame("frames: 4000 received"), None);
        assert_eq!(find_frame("frame x frame 1: y"), Some(8));
    }
}
