//! The low-pass a record's output went through when it was decimated from a faster rate, applied
//! to a prediction so that the model is compared with the record alike (`predict --output-filter`).
//!
//! A model predicts the output at the sample instants. A record made by simulating or measuring
//! at a higher rate and decimating carries the decimation filter's passband response as well.
//! A filter that is flat over the signal's band leaves no trace. One that droops does: MATLAB's
//! `decimate(y, 20, 'fir')` in one stage, at 15 kHz, is a 31-tap filter with a 375 Hz cutoff and a
//! wide transition band. Its gain is 1 − 9.5e-4 at 19.4 Hz, 1 − 6.4e-3 at 50.6 Hz and 1 − 5.5e-2 at
//! 150 Hz: about 1 − 2.5e-6·f² (f in Hz).
//!
//! `fir-decimate:factors=R1/R2/…[,identified_with=Q1/Q2/…][,order=N]`: the output was decimated
//! by R1, then R2, … (the record's rate fs is the last stage's output rate), each stage by MATLAB's
//! `decimate(y, r, 'fir')`:
//! - an order-N FIR low-pass (N even, default 30) `h = fir1(N, 1/r)`: Hamming window
//!   w\[n\] = 0.54 − 0.46·cos(2πn/N) times the ideal low-pass (1/r)·sinc((n − N/2)/r), scaled to unit
//!   DC gain;
//! - run with its delay compensated, so zero phase;
//! - stage i runs at fs_i = fs·R_i·R_(i+1)·…
//!
//! Its amplitude response is A_i(f) = h\[M\] + 2·Σ_(k=1..M) h\[M+k\]·cos(2πf·k/fs_i), M = N/2.
//!
//! A model identified on a record that went through a filter of its own has fitted that filter's
//! response too: `identified_with=Q1/Q2/…` names it (same stage rule, responses B_j), and the
//! prediction is filtered by the ratio H(f) = Π A_i(f) / Π B_j(f) (a denominator below 1e-6 gives 0;
//! without `identified_with`, H(f) = Π A_i(f)).
//!
//! The Bouc-Wen benchmark's generator decimates its multisines 2, 2, 5 (flat to 1.3e-3 up to
//! 150 Hz). Its official sine sweep was decimated by 20 in one stage: the published system,
//! simulated accurately on the sweep's input and decimated that way, matches the file to 9.4e-8 m,
//! against 2.6e-6 m read at the sample instants and 2.4e-6 m decimated 2, 2, 5
//! (`host-sim/evidence/boucwen_sweep.py`). A model
//! identified on the multisines is scored on that sweep with `factors=20,identified_with=2/2/5`.
//!
//! The prediction (at fs) is filtered in the frequency domain: H(f) multiplies every frequency of the
//! FFT of its even extension `y, reversed(y)`. The response is real and even, so this is zero
//! phase, and the even extension has no jump at either join. The result is exact for a prediction
//! band-limited to fs/2.

use rustfft::num_complex::Complex;

/// Default FIR order of MATLAB's `decimate(…, 'fir')`.
pub const DEFAULT_ORDER: usize = 30;

/// A validated output filter.
#[derive(Debug, Clone, PartialEq)]
pub struct OutputFilter {
    /// The decimation factors, first stage first.
    factors: Vec<usize>,
    /// The decimation factors of the record the model was identified on (empty: none).
    identified_with: Vec<usize>,
    /// FIR order N of every stage.
    order: usize,
}

impl OutputFilter {
    /// Parses `fir-decimate:factors=R1/R2/…[,identified_with=Q1/Q2/…][,order=N]`; errors name the
    /// key.
    pub fn parse(spec: &str) -> crate::Result<Self> {
        let (kind, rest) = spec.split_once(':').unwrap_or((spec, ""));
        if kind != "fir-decimate" {
            return Err(crate::Error::Usage(format!(
                "`{kind}`: unknown output filter (valid: fir-decimate:factors=R1/R2/…[,identified_with=Q1/Q2/…][,order=N])"
            )));
        }
        let mut factors = None;
        let mut identified_with = Vec::new();
        let mut order = DEFAULT_ORDER;
        for pair in rest.split(',').filter(|p| !p.is_empty()) {
            let (key, value) = pair
                .split_once('=')
                .ok_or_else(|| crate::Error::Usage(format!("`{pair}`: expected key=value")))?;
            match key {
                "factors" => factors = Some(parse_factors(key, value)?),
                "identified_with" => identified_with = parse_factors(key, value)?,
                "order" => {
                    order = match value.trim().parse::<usize>() {
                        Ok(n) if n >= 2 && n % 2 == 0 && n <= 10_000 => n,
                        _ => {
                            return Err(crate::Error::Usage(format!(
                                "order=`{value}`: expected an even FIR order 2…10000"
                            )))
                        }
                    }
                }
                _ => {
                    return Err(crate::Error::Usage(format!(
                        "`{key}`: unknown key (valid: factors, identified_with, order)"
                    )))
                }
            }
        }
        let factors = factors.ok_or_else(|| {
            crate::Error::Usage("fir-decimate: `factors` is required (e.g. factors=20)".into())
        })?;
        Ok(Self {
            factors,
            identified_with,
            order,
        })
    }

    /// H(f) at `f_hz` for a record at `fs_hz`: the record's chain over the identification record's.
    pub fn response(&self, f_hz: f64, fs_hz: f64) -> f64 {
        self.response_at_rate(fs_hz)(f_hz)
    }

    /// H as a function of frequency \[Hz\] for a record at `fs_hz` (the stages designed once).
    fn response_at_rate(&self, fs_hz: f64) -> impl Fn(f64) -> f64 {
        let record = Chain::new(&self.factors, self.order, fs_hz);
        let identified = Chain::new(&self.identified_with, self.order, fs_hz);
        move |f_hz| {
            let (numerator, denominator) = (record.response(f_hz), identified.response(f_hz));
            if denominator.abs() < 1e-6 {
                0.0
            } else {
                numerator / denominator
            }
        }
    }

    /// Filters `y`, sampled at `fs_hz`, by H (zero phase, through its even extension).
    pub fn apply(&self, y: &[f64], fs_hz: f64) -> Vec<f64> {
        let n = y.len();
        if n == 0 {
            return Vec::new();
        }
        let m = 2 * n;
        let mut spec: Vec<Complex<f64>> = y
            .iter()
            .chain(y.iter().rev())
            .map(|&v| Complex::new(v, 0.0))
            .collect();
        let mut planner = rustfft::FftPlanner::<f64>::new();
        planner.plan_fft_forward(m).process(&mut spec);
        let response = self.response_at_rate(fs_hz);
        for (k, bin) in spec.iter_mut().enumerate() {
            // Bin k and bin m − k are ±f: the same real gain keeps the series real.
            *bin *= response(k.min(m - k) as f64 * fs_hz / m as f64);
        }
        planner.plan_fft_inverse(m).process(&mut spec);
        spec[..n].iter().map(|c| c.re / m as f64).collect()
    }
}

/// Parses `R1/R2/…` of `key`: whole factors 2…1000.
fn parse_factors(key: &str, value: &str) -> crate::Result<Vec<usize>> {
    let parsed: Result<Vec<usize>, _> = value.split('/').map(|r| r.trim().parse()).collect();
    match parsed {
        Ok(f) if !f.is_empty() && f.iter().all(|r| (2..=1000).contains(r)) => Ok(f),
        _ => Err(crate::Error::Usage(format!(
            "{key}=`{value}`: expected whole factors 2…1000 separated by `/` (e.g. 20 or 2/2/5)"
        ))),
    }
}

/// A chain of decimation stages ending at a record rate: each stage's coefficients and input rate.
struct Chain {
    /// Per stage, first stage first: (`fir1(N, 1/r)`, its input rate \[Hz\]).
    stages: Vec<(Vec<f64>, f64)>,
}

impl Chain {
    fn new(factors: &[usize], order: usize, record_rate_hz: f64) -> Self {
        let mut rate = record_rate_hz * factors.iter().product::<usize>() as f64;
        let stages = factors
            .iter()
            .map(|&r| {
                let stage = (fir1(order, r), rate);
                rate /= r as f64;
                stage
            })
            .collect();
        Self { stages }
    }

    /// The product of the stages' amplitude responses at `f_hz` (1 for no stage).
    fn response(&self, f_hz: f64) -> f64 {
        self.stages
            .iter()
            .map(|(h, rate)| amplitude(h, f_hz / rate))
            .product()
    }
}

/// MATLAB's `fir1(order, 1/r)`: Hamming-windowed ideal low-pass with cutoff 1/r of Nyquist, unit
/// DC gain.
fn fir1(order: usize, r: usize) -> Vec<f64> {
    let cutoff = 1.0 / r as f64;
    let half = order as f64 / 2.0;
    let mut h: Vec<f64> = (0..=order)
        .map(|n| {
            let x = n as f64 - half;
            let ideal = if x == 0.0 {
                cutoff
            } else {
                (std::f64::consts::PI * cutoff * x).sin() / (std::f64::consts::PI * x)
            };
            let window = 0.54 - 0.46 * (2.0 * std::f64::consts::PI * n as f64 / order as f64).cos();
            ideal * window
        })
        .collect();
    let dc: f64 = h.iter().sum();
    for v in &mut h {
        *v /= dc;
    }
    h
}

/// The zero-phase amplitude response of a symmetric FIR `h` (odd length) at `f_per_sample` cycles
/// per sample.
fn amplitude(h: &[f64], f_per_sample: f64) -> f64 {
    let m = h.len() / 2;
    let w = 2.0 * std::f64::consts::PI * f_per_sample;
    h[m] + 2.0
        * (1..=m)
            .map(|k| h[m + k] * (w * k as f64).cos())
            .sum::<f64>()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fir1_matches_an_independent_design() {
        // scipy.signal.firwin(31, 1/20) and firwin(31, 1/2) (Hamming, scaled to unit DC gain).
        let h = fir1(30, 20);
        for (i, want) in [
            (0, 0.0017070784931335254),
            (7, 0.0264714571744417),
            (15, 0.07110328041787525),
        ] {
            assert!((h[i] - want).abs() < 1e-15, "h[{i}] = {} vs {want}", h[i]);
        }
        let h = fir1(30, 2);
        for (i, want) in [
            (1, 1.7580300581294008e-18),
            (14, 0.31561956332448227),
            (15, 0.5008082269469846),
        ] {
            assert!((h[i] - want).abs() < 1e-15, "h[{i}] = {} vs {want}", h[i]);
        }
    }

    #[test]
    fn one_stage_droops_and_the_staged_chain_is_flat() {
        // scipy.signal.freqz of the same filters: one stage of 20 at 15 kHz, and 2, 2, 5.
        let one = OutputFilter::parse("fir-decimate:factors=20").unwrap();
        let staged = OutputFilter::parse("fir-decimate:factors=2/2/5,order=30").unwrap();
        for (f, want) in [
            (19.4, -0.0009489232274080273),
            (50.6, -0.006439571168407543),
            (150.0, -0.05533219571579373),
        ] {
            let got = one.response(f, 750.0) - 1.0;
            assert!((got - want).abs() < 1e-12, "{f} Hz: {got} vs {want}");
        }
        let got = staged.response(150.0, 750.0) - 1.0;
        assert!((got - 0.0012576744067940293).abs() < 1e-12, "{got}");
        // Relative to the identification record's chain: the ratio of the two.
        let relative =
            OutputFilter::parse("fir-decimate:factors=20,identified_with=2/2/5").unwrap();
        let want = (1.0 - 0.05533219571579373) / (1.0 + 0.0012576744067940293);
        let got = relative.response(150.0, 750.0);
        assert!((got - want).abs() < 1e-12, "{got} vs {want}");
        let same = OutputFilter::parse("fir-decimate:factors=2/2/5,identified_with=2/2/5").unwrap();
        assert!((same.response(150.0, 750.0) - 1.0).abs() < 1e-14);
        assert!((one.response(0.0, 750.0) - 1.0).abs() < 1e-14);
    }

    #[test]
    fn a_sine_is_scaled_by_the_response_without_a_phase_shift() {
        let filter = OutputFilter::parse("fir-decimate:factors=20").unwrap();
        let fs = 750.0;
        // 50 Hz over 3 s, symmetric about the half samples at both ends: its even extension is
        // the same sinusoid (150 whole cycles), so no end effect blurs the comparison.
        let y: Vec<f64> = (0..2250)
            .map(|k| (2.0 * std::f64::consts::PI * 50.0 * (k as f64 + 0.5) / fs).cos())
            .collect();
        let out = filter.apply(&y, fs);
        let g = filter.response(50.0, fs);
        let worst = y
            .iter()
            .zip(&out)
            .map(|(a, b)| (g * a - b).abs())
            .fold(0.0, f64::max);
        assert!(worst < 1e-10, "worst {worst}");
        assert!((g - 1.0).abs() > 1e-3, "the test must see the droop");
    }

    #[test]
    fn bad_specs_name_the_key() {
        for (spec, says) in [
            ("fir:factors=20", "unknown output filter"),
            ("fir-decimate", "`factors` is required"),
            ("fir-decimate:factors=1", "factors=`1`"),
            ("fir-decimate:factors=2/x", "factors=`2/x`"),
            ("fir-decimate:factors=20,order=31", "order=`31`"),
            ("fir-decimate:factors=20,taps=31", "`taps`: unknown key"),
            ("fir-decimate:factors", "expected key=value"),
            (
                "fir-decimate:factors=20,identified_with=0",
                "identified_with=`0`",
            ),
        ] {
            let err = OutputFilter::parse(spec).unwrap_err().to_string();
            assert!(err.contains(says), "{spec}: {err}");
        }
    }
}
