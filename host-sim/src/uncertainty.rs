//! The uncertainty of a least-squares fit: per parameter its standard error, the parameters'
//! correlation matrix, and the prediction band (the RMS error the model is expected to make on a
//! new input of the same kind).
//!
//! # Equations
//! With the fitted samples k = 1..N, the residual r_k = y_k − ŷ_k (measured minus model, \[m\]) at
//! the optimum and the Jacobian g_k = ∂ŷ_k/∂p of the model's output with respect to the p
//! parameters *as written in the report's `params`* (so no further reparametrisation: a fit in
//! other coordinates hands over its Jacobian chained to these, the delta method),
//!
//! ```text
//! s²   = SSE / (N − p)                                  residual variance
//! C_iid = s²·(JᵀJ)⁻¹                                    textbook covariance (white residual)
//! Ω    = Σ_{|l|<L} (1 − |l|/L)·Σ_k x_k·x_{k+l}ᵀ,  x_k = g_k·r_k      Bartlett (Newey–West) long-run
//! C    = N/(N − p) · (JᵀJ)⁻¹·Ω·(JᵀJ)⁻¹ / (1 − b + b²/3),  b = L/N     covariance used
//! σ_i  = √C_ii,   ρ_ij = C_ij / (σ_i·σ_j)
//! band = √( s² + (1/N)·Σ_k g_kᵀ·C·g_k ) = √( s² + tr(C·JᵀJ)/N )
//! ```
//!
//! A measured record's residual is not white: it holds the model's own error, slow against the
//! sampling, so neighbouring samples are strongly correlated and C_iid would be far too small.
//! The sandwich C is heteroskedasticity- and autocorrelation-consistent (Newey & West 1987): Ω
//! sums the scores' autocovariances with Bartlett weights up to the bandwidth L, chosen from the
//! residual's lag-1 autocorrelation ρ by Andrews' (1991) AR(1) plug-in rule for the Bartlett kernel,
//! L = ⌈1.1447·(α·N)^(1/3)⌉ with α = 4ρ²/(1 − ρ²)², held within 1 ≤ L ≤ N/4. Ω is computed in
//! O(N·p²) as (1/L)·Σ_t S_t·S_tᵀ over the zero-padded windows S_t = Σ_{k=t}^{t+L−1} x_k (each pair
//! of samples l apart lies in L − |l| of them, which gives the Bartlett weights exactly). At the
//! optimum Σ_k x_k = 0, which biases Ω low by the factor 1 − b + b²/3 (Kiefer & Vogelsang 2005,
//! b = L/N); C is divided by it. For a white residual L is 1 or 2 and C is White's
//! heteroskedasticity-consistent covariance, close to C_iid. The basis reports ρ, L and the
//! geometric mean of σ_i / σ_iid,i (how much the autocorrelation inflated the standard errors).
//!
//! The band's first term is the residual's variance (noise and model error alike, as a new input
//! of the same kind will show them), its second the parameters' uncertainty carried through the
//! model on the fitted input, as the new input is of the same kind.
//!
//! These are local (linearised) figures: a parameter at a bound of its search range, or a fit held
//! to the compensator's sets by a constraint that binds, is not covered by them.

// Small dense linear algebra reads best with index loops.
#![allow(clippy::needless_range_loop)]

use serde_json::{json, Map, Value};

/// Andrews' constant of the Bartlett kernel's optimal bandwidth.
const ANDREWS_BARTLETT: f64 = 1.1447;

/// Largest bandwidth, as a share of the fitted samples.
const MAX_BANDWIDTH_SHARE: f64 = 0.25;

/// A pivot of the unit-diagonal normal matrix below this makes the parameters not identifiable
/// (their Jacobian columns are linearly dependent to about 1e-6 in correlation).
const SINGULAR_PIVOT: f64 = 1e-12;

/// One fitted parameter: its name in the report (a path into `params`: `bouc_wen.beta`,
/// `effects.creep_gain_m_per_v[0]`) and its value.
#[derive(Debug, Clone, PartialEq)]
pub struct Parameter {
    /// Path into the report's `params` (`.`-separated, `[i]` for an array element).
    pub name: String,
    /// Fitted value (SI).
    pub value: f64,
}

impl Parameter {
    /// A parameter named `name` with value `value`.
    pub fn new(name: impl Into<String>, value: f64) -> Self {
        Self {
            name: name.into(),
            value,
        }
    }
}

/// The uncertainty of one fit ([`estimate`]).
#[derive(Debug, Clone, PartialEq)]
pub struct Uncertainty {
    /// The parameters reported (the nuisance ones left out).
    pub parameters: Vec<Parameter>,
    /// Standard error of each (SI, as its parameter).
    pub standard_errors: Vec<f64>,
    /// Their correlation matrix.
    pub correlation: Vec<Vec<f64>>,
    /// The RMS error expected on a new input of the same kind \[m\].
    pub prediction_band_rms_m: f64,
    /// The basis of the figures.
    pub basis: Basis,
}

/// What the figures rest on.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Basis {
    /// Fitted samples N.
    pub samples: usize,
    /// Fitted parameters p (nuisance ones included).
    pub parameters: usize,
    /// √(SSE/(N − p)) \[m\].
    pub residual_std_m: f64,
    /// The residual's lag-1 autocorrelation ρ.
    pub residual_lag1_autocorrelation: f64,
    /// The Bartlett bandwidth L (samples).
    pub bartlett_lags: usize,
    /// Geometric mean over the parameters of σ / σ_iid.
    pub inflation_over_white: f64,
}

/// The Jacobian and residual of a fit at its optimum: `columns[j][k]` = ∂ŷ_k/∂p_j over the
/// fitted samples, `residual[k]` = y_k − ŷ_k \[m\]. The first `parameters.len()` columns are
/// reported; any further ones are nuisance parameters (e.g. per-record offsets), in the
/// covariance but not in the report.
#[derive(Debug, Clone)]
pub struct Linearised {
    /// The reported parameters.
    pub parameters: Vec<Parameter>,
    /// One column per parameter (reported first, then nuisance).
    pub columns: Vec<Vec<f64>>,
    /// Residual over the fitted samples \[m\].
    pub residual: Vec<f64>,
}

/// The residual's lag-1 autocorrelation Σ r_k·r_(k+1) / Σ r_k² (0 for a zero residual).
pub fn lag1_autocorrelation(r: &[f64]) -> f64 {
    let den: f64 = r.iter().map(|v| v * v).sum();
    if !(den > 0.0) {
        return 0.0;
    }
    r.windows(2).map(|w| w[0] * w[1]).sum::<f64>() / den
}

/// Andrews' AR(1) plug-in bandwidth of the Bartlett kernel for `n` samples with lag-1
/// autocorrelation `rho` (module doc), held within 1..=N/4.
pub fn bartlett_bandwidth(rho: f64, n: usize) -> usize {
    let rho = rho.clamp(-0.999_999, 0.999_999);
    let alpha = 4.0 * rho * rho / (1.0 - rho * rho).powi(2);
    let l = (ANDREWS_BARTLETT * (alpha * n as f64).cbrt()).ceil();
    let max = ((MAX_BANDWIDTH_SHARE * n as f64).floor() as usize).max(1);
    if l.is_finite() {
        (l as usize).clamp(1, max)
    } else {
        max
    }
}

/// The inverse of the symmetric positive definite `a` (p × p), by Gauss–Jordan with partial
/// pivoting on its unit-diagonal scaling; an error when a column is zero or the columns are
/// linearly dependent (`names` name them).
fn inverse(a: &[Vec<f64>], names: &[String]) -> crate::Result<Vec<Vec<f64>>> {
    let p = a.len();
    let mut d = vec![0.0; p];
    for i in 0..p {
        if !(a[i][i] > 0.0) || !a[i][i].is_finite() {
            return Err(crate::Error::Fit(format!(
                "the model's output does not depend on {} at the fit (its Jacobian column is zero)",
                names.get(i).map_or("a nuisance parameter", String::as_str)
            )));
        }
        d[i] = 1.0 / a[i][i].sqrt();
    }
    // [A | I] with A scaled to a unit diagonal.
    let mut m: Vec<Vec<f64>> = (0..p)
        .map(|i| {
            let mut row: Vec<f64> = (0..p).map(|j| a[i][j] * d[i] * d[j]).collect();
            row.extend((0..p).map(|j| if i == j { 1.0 } else { 0.0 }));
            row
        })
        .collect();
    for c in 0..p {
        let pivot = (c..p)
            .max_by(|&x, &y| m[x][c].abs().total_cmp(&m[y][c].abs()))
            .unwrap_or(c);
        if !(m[pivot][c].abs() > SINGULAR_PIVOT) {
            return Err(crate::Error::Fit(format!(
                "the parameters are not identifiable from this record: {} is a linear combination \
                 of the others to within 1e-12 (its Jacobian column)",
                names.get(c).map_or("a nuisance parameter", String::as_str)
            )));
        }
        m.swap(c, pivot);
        let inv = 1.0 / m[c][c];
        for v in m[c].iter_mut() {
            *v *= inv;
        }
        for r in 0..p {
            if r != c {
                let f = m[r][c];
                if f != 0.0 {
                    for j in 0..2 * p {
                        m[r][j] -= f * m[c][j];
                    }
                }
            }
        }
    }
    Ok((0..p)
        .map(|i| (0..p).map(|j| m[i][p + j] * d[i] * d[j]).collect())
        .collect())
}

fn product(a: &[Vec<f64>], b: &[Vec<f64>]) -> Vec<Vec<f64>> {
    let p = a.len();
    (0..p)
        .map(|i| {
            (0..p)
                .map(|j| (0..p).map(|l| a[i][l] * b[l][j]).sum())
                .collect()
        })
        .collect()
}

/// The uncertainty of a fit from its Jacobian and residual at the optimum (module doc). An error
/// says why it cannot be given: fewer samples than parameters, a non-finite entry, parameters the
/// record does not identify.
pub fn estimate(fit: &Linearised) -> crate::Result<Uncertainty> {
    let p = fit.columns.len();
    let n = fit.residual.len();
    let reported = fit.parameters.len();
    if reported > p {
        return Err(crate::Error::Fit(
            "fewer Jacobian columns than parameters".into(),
        ));
    }
    if n <= p {
        return Err(crate::Error::Fit(format!(
            "{n} fitted samples for {p} parameters"
        )));
    }
    if fit.columns.iter().any(|c| c.len() != n) {
        return Err(crate::Error::Fit(
            "a Jacobian column and the residual differ in length".into(),
        ));
    }
    if let Some(k) = fit.residual.iter().position(|v| !v.is_finite()) {
        return Err(crate::Error::Fit(format!(
            "the residual is not finite at fitted sample {k}"
        )));
    }
    for (j, c) in fit.columns.iter().enumerate() {
        if let Some(k) = c.iter().position(|v| !v.is_finite()) {
            let name = fit
                .parameters
                .get(j)
                .map_or("a nuisance parameter", |q| q.name.as_str());
            return Err(crate::Error::Fit(format!(
                "the output's derivative by {name} is not finite at fitted sample {k}"
            )));
        }
    }
    let mut names: Vec<String> = fit.parameters.iter().map(|q| q.name.clone()).collect();
    names.resize(p, "a nuisance parameter".into());
    // JᵀJ.
    let mut jtj = vec![vec![0.0f64; p]; p];
    for a in 0..p {
        for b in a..p {
            let s: f64 = fit.columns[a]
                .iter()
                .zip(&fit.columns[b])
                .map(|(x, y)| x * y)
                .sum();
            jtj[a][b] = s;
            jtj[b][a] = s;
        }
    }
    let jtj_inv = inverse(&jtj, &names)?;
    let sse: f64 = fit.residual.iter().map(|v| v * v).sum();
    let s2 = sse / (n - p) as f64;
    // Bartlett long-run covariance of the scores x_k = g_k·r_k from the zero-padded windows.
    let rho = lag1_autocorrelation(&fit.residual);
    let lags = bartlett_bandwidth(rho, n);
    let mut prefix = vec![vec![0.0f64; p]; n + 1];
    for k in 0..n {
        let r = fit.residual[k];
        for j in 0..p {
            prefix[k + 1][j] = prefix[k][j] + fit.columns[j][k] * r;
        }
    }
    let mut omega = vec![vec![0.0f64; p]; p];
    let mut s = vec![0.0f64; p];
    for t in -(lags as isize) + 1..n as isize {
        let hi = (t + lags as isize).min(n as isize) as usize;
        let lo = t.max(0) as usize;
        for j in 0..p {
            s[j] = prefix[hi][j] - prefix[lo][j];
        }
        for a in 0..p {
            for b in a..p {
                omega[a][b] += s[a] * s[b];
            }
        }
    }
    let b = lags as f64 / n as f64;
    let scale = n as f64 / (n - p) as f64 / (lags as f64 * (1.0 - b + b * b / 3.0));
    for a in 0..p {
        for c in a..p {
            omega[a][c] *= scale;
            omega[c][a] = omega[a][c];
        }
    }
    let cov = product(&product(&jtj_inv, &omega), &jtj_inv);
    let sigma: Vec<f64> = (0..p).map(|i| cov[i][i].max(0.0).sqrt()).collect();
    let trace: f64 = (0..p)
        .map(|i| (0..p).map(|j| cov[i][j] * jtj[j][i]).sum::<f64>())
        .sum();
    let band = (s2 + trace.max(0.0) / n as f64).sqrt();
    let inflation = {
        let logs: Vec<f64> = (0..reported)
            .filter(|&i| jtj_inv[i][i] > 0.0 && sigma[i] > 0.0)
            .map(|i| (sigma[i] / (s2 * jtj_inv[i][i]).sqrt()).ln())
            .collect();
        if logs.is_empty() {
            f64::NAN
        } else {
            (logs.iter().sum::<f64>() / logs.len() as f64).exp()
        }
    };
    let correlation = (0..reported)
        .map(|i| {
            (0..reported)
                .map(|j| {
                    let d = sigma[i] * sigma[j];
                    if d > 0.0 {
                        (cov[i][j] / d).clamp(-1.0, 1.0)
                    } else if i == j {
                        1.0
                    } else {
                        0.0
                    }
                })
                .collect()
        })
        .collect();
    if !band.is_finite() || sigma.iter().any(|v| !v.is_finite()) {
        return Err(crate::Error::Fit("the covariance is not finite".into()));
    }
    Ok(Uncertainty {
        parameters: fit.parameters.clone(),
        standard_errors: sigma[..reported].to_vec(),
        correlation,
        prediction_band_rms_m: band,
        basis: Basis {
            samples: n,
            parameters: p,
            residual_std_m: s2.sqrt(),
            residual_lag1_autocorrelation: rho,
            bartlett_lags: lags,
            inflation_over_white: inflation,
        },
    })
}

/// Splits `a.b[2]` into the path (`a`, `b`) and the array index (`Some(2)`).
fn path_of(name: &str) -> (Vec<&str>, Option<usize>) {
    let (path, index) = match name.strip_suffix(']').and_then(|s| s.rsplit_once('[')) {
        Some((p, i)) => (p, i.parse().ok()),
        None => (name, None),
    };
    (path.split('.').collect(), index)
}

impl Uncertainty {
    /// The standard errors nested as the report's `params` (an array element's standard error at
    /// its index of an array as long as the largest index reported, `null` elsewhere).
    pub fn nested(&self) -> Value {
        let mut root = Value::Object(Map::new());
        for (q, &se) in self.parameters.iter().zip(&self.standard_errors) {
            let (path, index) = path_of(&q.name);
            let mut node = &mut root;
            for (i, key) in path.iter().enumerate() {
                let last = i + 1 == path.len();
                let Value::Object(map) = node else { break };
                let entry = map.entry(key.to_string()).or_insert_with(|| {
                    if last && index.is_some() {
                        Value::Array(Vec::new())
                    } else if last {
                        Value::Null
                    } else {
                        Value::Object(Map::new())
                    }
                });
                if last {
                    match (entry, index) {
                        (Value::Array(items), Some(at)) => {
                            if items.len() <= at {
                                items.resize(at + 1, Value::Null);
                            }
                            items[at] = json!(se);
                        }
                        (slot, _) => *slot = json!(se),
                    }
                    break;
                }
                node = entry;
            }
        }
        root
    }

    /// The report's keys: `uncertainty` (standard errors nested as `params`), `correlation`
    /// (`names` and `matrix`), `prediction_band_rms_m` and `uncertainty_basis`.
    pub fn report_keys(&self) -> Map<String, Value> {
        let mut m = Map::new();
        m.insert("uncertainty".into(), self.nested());
        m.insert(
            "correlation".into(),
            json!({
                "names": self.parameters.iter().map(|q| q.name.clone()).collect::<Vec<_>>(),
                "matrix": self.correlation,
            }),
        );
        m.insert(
            "prediction_band_rms_m".into(),
            json!(self.prediction_band_rms_m),
        );
        m.insert("uncertainty_basis".into(), json!(self.basis));
        m
    }

    /// The parameters as `name = value ± standard error`, one per line, each line prefixed.
    pub fn lines(&self, prefix: &str) -> Vec<String> {
        let mut out: Vec<String> = self
            .parameters
            .iter()
            .zip(&self.standard_errors)
            .map(|(q, se)| format!("{prefix}{} = {:.5e} ± {:.2e}", q.name, q.value, se))
            .collect();
        out.push(format!(
            "{prefix}prediction band: rms {:.4e} m (Bartlett lags {}, residual lag-1 autocorrelation {:.3})",
            self.prediction_band_rms_m,
            self.basis.bartlett_lags,
            self.basis.residual_lag1_autocorrelation
        ));
        out
    }
}

/// The report's keys for a fit whose uncertainty could not be given: `uncertainty`,
/// `correlation` and `prediction_band_rms_m` null, and `uncertainty_not_computed` saying why.
pub fn missing_keys(why: &str) -> Map<String, Value> {
    let mut m = Map::new();
    for key in ["uncertainty", "correlation", "prediction_band_rms_m"] {
        m.insert(key.into(), Value::Null);
    }
    m.insert("uncertainty_not_computed".into(), json!(why));
    m
}

/// The report keys of `u` ([`Uncertainty::report_keys`] or [`missing_keys`]).
pub fn keys_of(u: &crate::Result<Uncertainty>) -> Map<String, Value> {
    match u {
        Ok(u) => u.report_keys(),
        Err(why) => missing_keys(&why.to_string()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand_chacha::ChaCha8Rng;
    use rand_core::{RngCore, SeedableRng};

    fn normal(rng: &mut ChaCha8Rng) -> f64 {
        // Box–Muller.
        let u1 = (rng.next_u64() >> 11) as f64 / (1u64 << 53) as f64;
        let u2 = (rng.next_u64() >> 11) as f64 / (1u64 << 53) as f64;
        (-2.0 * (1.0 - u1).ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
    }

    /// A straight line y = a + b·x with white noise: the standard errors are the textbook ones.
    #[test]
    fn a_straight_line_with_white_noise_has_the_textbook_standard_errors() {
        let n = 4000;
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let x: Vec<f64> = (0..n).map(|k| k as f64 / n as f64).collect();
        let y: Vec<f64> = x
            .iter()
            .map(|x| 1.0 + 2.0 * x + 0.1 * normal(&mut rng))
            .collect();
        // Least squares.
        let (mx, my) = (
            x.iter().sum::<f64>() / n as f64,
            y.iter().sum::<f64>() / n as f64,
        );
        let sxx: f64 = x.iter().map(|v| (v - mx).powi(2)).sum();
        let b = x
            .iter()
            .zip(&y)
            .map(|(x, y)| (x - mx) * (y - my))
            .sum::<f64>()
            / sxx;
        let a = my - b * mx;
        let r: Vec<f64> = x.iter().zip(&y).map(|(x, y)| y - a - b * x).collect();
        let fit = Linearised {
            parameters: vec![Parameter::new("a", a), Parameter::new("b", b)],
            columns: vec![vec![1.0; n], x.clone()],
            residual: r.clone(),
        };
        let u = estimate(&fit).unwrap();
        let s = (r.iter().map(|v| v * v).sum::<f64>() / (n - 2) as f64).sqrt();
        let se_b = s / sxx.sqrt();
        let se_a = s * (1.0 / n as f64 + mx * mx / sxx).sqrt();
        assert!(u.basis.bartlett_lags <= 3, "{:?}", u.basis);
        for (got, want) in u.standard_errors.iter().zip([se_a, se_b]) {
            assert!((got / want - 1.0).abs() < 0.1, "{got} vs {want}");
        }
        // corr(a, b) = −x̄/√(x̄² + Sxx/n)
        let want = -mx / (mx * mx + sxx / n as f64).sqrt();
        assert!((u.correlation[0][1] - want).abs() < 0.05);
        let band = (s * s * (1.0 + 2.0 / n as f64)).sqrt();
        assert!((u.prediction_band_rms_m / band - 1.0).abs() < 0.05);
    }

    /// An AR(1) noise (ρ = 0.95) widens the mean's standard error by √((1 + ρ)/(1 − ρ)) ≈ 6.2; the
    /// white-noise formula would not.
    #[test]
    fn autocorrelated_noise_widens_the_standard_error_by_the_long_run_factor() {
        let n = 20000;
        let rho: f64 = 0.95;
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let mut e = 0.0;
        let y: Vec<f64> = (0..n)
            .map(|_| {
                e = rho * e + (1.0 - rho * rho).sqrt() * normal(&mut rng);
                e
            })
            .collect();
        let mean = y.iter().sum::<f64>() / n as f64;
        let fit = Linearised {
            parameters: vec![Parameter::new("static_map.offset_m", mean)],
            columns: vec![vec![1.0; n]],
            residual: y.iter().map(|v| v - mean).collect(),
        };
        let u = estimate(&fit).unwrap();
        let white = 1.0 / (n as f64).sqrt();
        let want = white * ((1.0 + rho) / (1.0 - rho)).sqrt();
        let got = u.standard_errors[0];
        assert!((got / want - 1.0).abs() < 0.25, "{got} vs {want}");
        assert!(u.basis.inflation_over_white > 4.0);
    }

    #[test]
    fn dependent_columns_are_refused_naming_the_parameter() {
        let n = 100;
        let x: Vec<f64> = (0..n).map(|k| k as f64).collect();
        let fit = Linearised {
            parameters: vec![
                Parameter::new("a", 0.0),
                Parameter::new("b", 0.0),
                Parameter::new("c", 0.0),
            ],
            columns: vec![
                vec![1.0; n],
                x.clone(),
                x.iter().map(|v| 2.0 * v + 1.0).collect(),
            ],
            residual: (0..n).map(|k| (k as f64).sin()).collect(),
        };
        let e = estimate(&fit).unwrap_err().to_string();
        assert!(e.contains("not identifiable") && e.contains('c'), "{e}");
        let zero = Linearised {
            parameters: vec![Parameter::new("a", 0.0), Parameter::new("b", 0.0)],
            columns: vec![vec![1.0; n], vec![0.0; n]],
            residual: (0..n).map(|k| (k as f64).sin()).collect(),
        };
        assert!(estimate(&zero)
            .unwrap_err()
            .to_string()
            .contains("does not depend on b"));
    }

    #[test]
    fn standard_errors_nest_as_the_parameters() {
        let u = Uncertainty {
            parameters: vec![
                Parameter::new("bouc_wen.beta", 1.0),
                Parameter::new("static_map.k1_m_per_v", 1e-7),
                Parameter::new("effects.creep_gain_m_per_v[1]", 1e-9),
            ],
            standard_errors: vec![0.1, 1e-9, 1e-11],
            correlation: vec![vec![1.0, 0.0, 0.0]; 3],
            prediction_band_rms_m: 1e-8,
            basis: Basis {
                samples: 10,
                parameters: 3,
                residual_std_m: 1e-8,
                residual_lag1_autocorrelation: 0.0,
                bartlett_lags: 1,
                inflation_over_white: 1.0,
            },
        };
        assert_eq!(
            u.nested(),
            json!({"bouc_wen": {"beta": 0.1}, "static_map": {"k1_m_per_v": 1e-9},
                   "effects": {"creep_gain_m_per_v": [null, 1e-11]}})
        );
    }
}
