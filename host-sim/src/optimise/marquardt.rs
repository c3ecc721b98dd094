//! Levenberg–Marquardt with Marquardt's scaling (Marquardt, "An Algorithm for Least-Squares
//! Estimation of Nonlinear Parameters", J. SIAM 11, 1963; Nocedal & Wright, *Numerical
//! Optimization*, 2nd ed., §10.3) over a [`LeastSquares`] problem that supplies the normal
//! equations itself (sensitivity equations, a variable-projection Jacobian or forward
//! differences: each caller's own), inside a box of bounds.
//!
//! Residual r(θ), SSE S(θ) = Σ r², Jacobian J = ∂r/∂θ, gradient g = Jᵀr (half the SSE's).
//! Per iteration, up to [`Marquardt::tries`] trial steps d solving
//! (JᵀJ + λ·diag(max(JᵀJ_ii, floor)))·d = −g on the free parameters (with
//! [`Marquardt::hold_at_bounds`] a parameter at a bound whose gradient points out of the box,
//! θ_j ≤ lo with g_j > 0 or θ_j ≥ hi with g_j < 0, keeps d_j = 0); a singular system multiplies λ
//! by [`Marquardt::singular_factor`]. The trial θ + d is clamped into the bounds. It is accepted
//! when S(trial) < S(θ): then λ ← max(λ/3, λ_min); else λ ← 4λ and the next try.
//!
//! Stopping: after [`Marquardt::iterations`] iterations; when the problem gives no normal
//! equations; when an iteration accepts no step (unless [`LeastSquares::retry`] takes another
//! Jacobian first: λ starts again from its initial value); when an accepted step's relative gain
//! (S − S_trial)/S is at most [`Marquardt::min_gain`]; when [`Marquardt::small_steps`] accepted steps in a
//! row each gain less than its relative threshold; and, with [`Marquardt::predicted_gain`] = τ, when
//! the linear model promises a reduction −(2·dᵀg + dᵀJᵀJ·d) ≤ τ·S (the step's end, before it is
//! tried). A start whose SSE is not finite is returned as it is.

/// The normal equations of a least-squares problem at θ: JᵀJ and the gradient g = Jᵀr
/// (J = ∂r/∂θ).
#[derive(Debug, Clone, PartialEq)]
pub struct NormalEquations {
    /// JᵀJ (symmetric, dim × dim).
    pub jtj: Vec<Vec<f64>>,
    /// g = Jᵀr.
    pub gradient: Vec<f64>,
}

impl NormalEquations {
    /// The SSE reduction the linear model promises for the step d: −(2·dᵀg + dᵀJᵀJ·d).
    pub fn predicted_gain(&self, d: &[f64]) -> f64 {
        let mut gain = 0.0;
        for (a, row) in self.jtj.iter().enumerate() {
            let jd: f64 = row.iter().zip(d).map(|(j, dv)| j * dv).sum();
            gain -= d[a] * (2.0 * self.gradient[a] + jd);
        }
        gain
    }
}

/// A least-squares problem for [`Marquardt::run`]: its SSE and its normal equations, and what it
/// does with accepted steps.
pub trait LeastSquares {
    /// The SSE at θ. It may stop summing once the sum passes `abandon_above` and return that
    /// partial sum (the step is then rejected all the same).
    fn sse(&mut self, theta: &[f64], abandon_above: f64) -> f64;

    /// The normal equations at θ (the last accepted point); `None` stops the fit.
    fn normal_equations(&mut self, theta: &[f64]) -> Option<NormalEquations>;

    /// Called at the start of each iteration (progress).
    fn iteration(&mut self) {}

    /// Called with each tried step's damping and SSE (traces).
    fn tried(&mut self, _lambda: f64, _sse: f64) {}

    /// Called when a step is accepted: the new θ, its SSE, its relative gain and the damping for
    /// the next step.
    fn accepted(&mut self, _theta: &[f64], _sse: f64, _gain: f64, _lambda: f64) {}

    /// Whether to take the normal equations again after an iteration that accepted no step (the
    /// problem changes how it builds them, e.g. larger difference steps); default no.
    fn retry(&mut self) -> bool {
        false
    }
}

/// The settings of one Levenberg–Marquardt run (module doc).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Marquardt {
    /// Initial damping λ (and the damping a retry starts from).
    pub lambda: f64,
    /// Smallest damping after an accepted step.
    pub lambda_min: f64,
    /// Floor of the Marquardt scale diag(JᵀJ).
    pub scale_floor: f64,
    /// Trial steps per iteration.
    pub tries: usize,
    /// Factor on λ when the damped system is singular.
    pub singular_factor: f64,
    /// At most this many iterations.
    pub iterations: usize,
    /// An accepted step whose relative gain is not above this ends the fit (after it is taken).
    pub min_gain: f64,
    /// (relative gain, count): stop after `count` accepted steps in a row each gaining less.
    pub small_steps: Option<(f64, usize)>,
    /// τ: stop when the linear model promises a reduction of at most τ·SSE.
    pub predicted_gain: Option<f64>,
    /// Hold a parameter at a bound whose gradient points out of the box (else only clamp).
    pub hold_at_bounds: bool,
}

impl Marquardt {
    /// Fits `problem` from `theta` (whose SSE is `sse`) inside `bounds`; returns the last accepted
    /// θ and its SSE.
    pub fn run(
        &self,
        problem: &mut impl LeastSquares,
        mut theta: Vec<f64>,
        mut sse: f64,
        bounds: &[(f64, f64)],
    ) -> (Vec<f64>, f64) {
        if !sse.is_finite() {
            return (theta, sse);
        }
        let mut lambda = self.lambda;
        let mut small = 0;
        for _ in 0..self.iterations {
            problem.iteration();
            let Some(normal) = problem.normal_equations(&theta) else {
                break;
            };
            let mut improved = false;
            for _ in 0..self.tries {
                let Some(d) = self.damped_step(&normal, &theta, bounds, lambda) else {
                    lambda *= self.singular_factor;
                    continue;
                };
                if let Some(tau) = self.predicted_gain {
                    if normal.predicted_gain(&d) <= tau * sse {
                        break;
                    }
                }
                let trial: Vec<f64> = theta
                    .iter()
                    .zip(&d)
                    .zip(bounds)
                    .map(|((a, b), &(lo, hi))| (a + b).clamp(lo, hi))
                    .collect();
                let st = problem.sse(&trial, sse);
                problem.tried(lambda, st);
                if st < sse {
                    let gain = (sse - st) / sse;
                    theta = trial;
                    sse = st;
                    lambda = (lambda / 3.0).max(self.lambda_min);
                    improved = gain > self.min_gain;
                    small = match self.small_steps {
                        Some((below, _)) if gain < below => small + 1,
                        _ => 0,
                    };
                    problem.accepted(&theta, sse, gain, lambda);
                    break;
                }
                lambda *= 4.0;
            }
            if !improved && problem.retry() {
                lambda = self.lambda;
                continue;
            }
            if !improved || self.small_steps.is_some_and(|(_, count)| small >= count) {
                break;
            }
        }
        (theta, sse)
    }

    /// The damped step d (module doc); `None` when the damped system is singular.
    fn damped_step(
        &self,
        normal: &NormalEquations,
        theta: &[f64],
        bounds: &[(f64, f64)],
        lambda: f64,
    ) -> Option<Vec<f64>> {
        let dim = theta.len();
        let free: Vec<usize> = (0..dim)
            .filter(|&j| {
                let (lo, hi) = bounds[j];
                let g = normal.gradient[j];
                !(self.hold_at_bounds
                    && ((theta[j] <= lo && g > 0.0) || (theta[j] >= hi && g < 0.0)))
            })
            .collect();
        let mut aug: Vec<Vec<f64>> = free
            .iter()
            .map(|&a| {
                let mut row: Vec<f64> = free.iter().map(|&b| normal.jtj[a][b]).collect();
                row.push(-normal.gradient[a]);
                row
            })
            .collect();
        for (i, &a) in free.iter().enumerate() {
            aug[i][i] += lambda * normal.jtj[a][a].max(self.scale_floor);
        }
        let solved = super::linear::solve(&mut aug, free.len())?;
        let mut d = vec![0.0; dim];
        for (&j, v) in free.iter().zip(solved) {
            d[j] = v;
        }
        Some(d)
    }
}
