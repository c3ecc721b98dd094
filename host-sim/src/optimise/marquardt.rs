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

#[cfg(test)]
mod tests {
    use super::*;

    /// y = a·e^(−b·t) on 40 samples, exact data; counts the calls.
    struct Decay {
        t: Vec<f64>,
        y: Vec<f64>,
        normal_calls: usize,
        /// The first this-many normal equations are useless (zero), until a retry.
        useless: usize,
        retries: usize,
    }

    impl Decay {
        fn new(a: f64, b: f64) -> Self {
            let t: Vec<f64> = (0..40).map(|k| 0.05 * k as f64).collect();
            let y = t.iter().map(|&t| a * (-b * t).exp()).collect();
            Self {
                t,
                y,
                normal_calls: 0,
                useless: 0,
                retries: 0,
            }
        }
        fn residual(&self, th: &[f64]) -> Vec<f64> {
            self.t
                .iter()
                .zip(&self.y)
                .map(|(&t, &y)| th[0] * (-th[1] * t).exp() - y)
                .collect()
        }
    }

    impl LeastSquares for Decay {
        fn sse(&mut self, th: &[f64], _: f64) -> f64 {
            self.residual(th).iter().map(|r| r * r).sum()
        }
        fn normal_equations(&mut self, th: &[f64]) -> Option<NormalEquations> {
            self.normal_calls += 1;
            let mut jtj = vec![vec![0.0; 2]; 2];
            let mut gradient = vec![0.0; 2];
            if self.useless > 0 {
                return Some(NormalEquations { jtj, gradient });
            }
            for (&t, r) in self.t.iter().zip(self.residual(th)) {
                let e = (-th[1] * t).exp();
                let j = [e, -th[0] * t * e];
                for a in 0..2 {
                    gradient[a] += j[a] * r;
                    for b in 0..2 {
                        jtj[a][b] += j[a] * j[b];
                    }
                }
            }
            Some(NormalEquations { jtj, gradient })
        }
        fn retry(&mut self) -> bool {
            if self.useless == 0 {
                return false;
            }
            self.useless -= 1;
            self.retries += 1;
            true
        }
    }

    fn settings() -> Marquardt {
        Marquardt {
            lambda: 1e-3,
            lambda_min: 1e-12,
            scale_floor: 1e-30,
            tries: 10,
            singular_factor: 10.0,
            iterations: 100,
            min_gain: 0.0,
            small_steps: None,
            predicted_gain: None,
            hold_at_bounds: false,
        }
    }

    const BOX: [(f64, f64); 2] = [(0.0, 10.0), (0.0, 10.0)];

    #[test]
    fn fits_an_exponential_decay_from_afar() {
        let mut p = Decay::new(2.0, 1.5);
        let start = vec![0.5, 0.2];
        let s0 = p.sse(&start, f64::INFINITY);
        let (th, sse) = settings().run(&mut p, start, s0, &BOX);
        assert!(
            (th[0] - 2.0).abs() < 1e-6 && (th[1] - 1.5).abs() < 1e-6,
            "{th:?}"
        );
        assert!(sse < 1e-12 * s0, "{sse:e}");
    }

    #[test]
    fn a_parameter_pushing_out_of_the_box_is_held_at_its_bound() {
        // The best b is 1.5, above the box's 1.0: b stays at 1.0, a is the best for it.
        let mut p = Decay::new(2.0, 1.5);
        let bounds = [(0.0, 10.0), (0.0, 1.0)];
        let start = vec![1.0, 1.0];
        let s0 = p.sse(&start, f64::INFINITY);
        let held = Marquardt {
            hold_at_bounds: true,
            ..settings()
        };
        let (th, _) = held.run(&mut p, start, s0, &bounds);
        assert_eq!(th[1], 1.0);
        // ∂SSE/∂a = 0 at b = 1: a = Σ y·e^(−t) / Σ e^(−2t).
        let num: f64 = p.t.iter().zip(&p.y).map(|(t, y)| y * (-t).exp()).sum();
        let den: f64 = p.t.iter().map(|t| (-2.0 * t).exp()).sum();
        assert!((th[0] - num / den).abs() < 1e-9, "{th:?}");
    }

    #[test]
    fn an_iteration_without_a_step_takes_the_normal_equations_again_when_asked() {
        let mut p = Decay::new(2.0, 1.5);
        p.useless = 2;
        let start = vec![0.5, 0.2];
        let s0 = p.sse(&start, f64::INFINITY);
        let (th, _) = settings().run(&mut p, start, s0, &BOX);
        assert_eq!(p.retries, 2);
        assert!((th[0] - 2.0).abs() < 1e-6, "{th:?}");
        // Without a retry the fit stops at the start.
        let mut q = Decay::new(2.0, 1.5);
        q.useless = 1;
        let mut once = Marquardt {
            iterations: 1,
            ..settings()
        };
        let (th, sse) = once.run(&mut q, vec![0.5, 0.2], s0, &BOX);
        assert_eq!((th, sse), (vec![0.5, 0.2], s0));
        once.iterations = 0;
        assert_eq!(once.run(&mut q, vec![0.5, 0.2], s0, &BOX).1, s0);
    }

    #[test]
    fn a_start_without_a_finite_sse_is_returned_as_it_is() {
        let mut p = Decay::new(2.0, 1.5);
        let (th, sse) = settings().run(&mut p, vec![0.5, 0.2], f64::NAN, &BOX);
        assert_eq!(th, vec![0.5, 0.2]);
        assert!(sse.is_nan());
        assert_eq!(p.normal_calls, 0);
    }

    #[test]
    fn small_gains_in_a_row_stop_the_fit() {
        let start = vec![0.5, 0.2];
        let mut free = Decay::new(2.0, 1.5);
        let s0 = free.sse(&start, f64::INFINITY);
        settings().run(&mut free, start.clone(), s0, &BOX);
        let mut stopped = Decay::new(2.0, 1.5);
        let early = Marquardt {
            small_steps: Some((1.0, 2)),
            ..settings()
        };
        early.run(&mut stopped, start, s0, &BOX);
        // Every gain is below 100 %: two accepted steps, then the stop.
        assert_eq!(stopped.normal_calls, 2);
        assert!(free.normal_calls > 2);
    }
}
