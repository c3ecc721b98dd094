//! Differential evolution (Storn & Price, "Differential Evolution – A Simple and Efficient
//! Heuristic for Global Optimization over Continuous Spaces", J. Global Optim. 11, 1997), in the
//! current-to-best/1 form with binomial crossover, over a box of bounds.
//!
//! Per generation and member i (best member b, donors r1, r2 drawn uniformly from the population;
//! with [`Evolution::distinct_donors`] r1 ≠ i and r2 ∉ {i, r1}):
//! mutant v_j = x_ij + F·(x_bj − x_ij) + F·(x_r1,j − x_r2,j); trial t_j = v_j where j = j_rand or a
//! uniform draw is below CR, else x_ij ([`Evolution::crossover`]; without crossover t = v and no
//! draw is made). A coordinate outside [lo, hi] is clamped to the bound, or set back between the
//! parent and the bound it crossed: lo + (x_ij − lo)·U or hi − (hi − x_ij)·U ([`Boundary`]).
//! The trial replaces its parent when its SSE is not larger (t ≤ x); the objective is handed the
//! parent's SSE and may stop summing once it passes it (the selection is then the same).
//!
//! Stopping: after [`Evolution::generations`] generations, or when the best SSE gained less than a
//! relative `gain` in `generations` generations in a row ([`Stall`]), or when the worst member is
//! within a factor 1 + ε of the best ([`Evolution::spread`]).
//!
//! Random numbers: one seeded [`ChaCha8Rng`] per run, the caller's, so a run is reproducible for
//! a seed; uniform draws in [0, 1) from the top 53 bits of a 64-bit draw ([`uniform`]), indices as
//! a 64-bit draw modulo the count. The trials of a generation are evaluated in parallel (rayon).

use rand_chacha::ChaCha8Rng;
use rand_core::RngCore;
use rayon::prelude::*;

/// A uniform draw in [0, 1): the top 53 bits of a 64-bit draw over 2⁵³.
pub fn uniform(rng: &mut ChaCha8Rng) -> f64 {
    (rng.next_u64() >> 11) as f64 / (1u64 << 53) as f64
}

/// A uniform index in 0..count (a 64-bit draw modulo `count`).
fn index(rng: &mut ChaCha8Rng, count: usize) -> usize {
    (rng.next_u64() % count as u64) as usize
}

/// `size` members drawn uniformly inside `bounds` (coordinate by coordinate, member by member).
pub fn random_population(
    bounds: &[(f64, f64)],
    size: usize,
    rng: &mut ChaCha8Rng,
) -> Vec<Vec<f64>> {
    (0..size)
        .map(|_| {
            bounds
                .iter()
                .map(|&(lo, hi)| lo + (hi - lo) * uniform(rng))
                .collect()
        })
        .collect()
}

/// The index of the smallest SSE (the first of equal ones; 0 when empty).
pub fn best_index(sse: &[f64]) -> usize {
    (0..sse.len())
        .min_by(|&a, &b| sse[a].total_cmp(&sse[b]))
        .unwrap_or(0)
}

/// What a coordinate of a mutant outside its bounds becomes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Boundary {
    /// The bound it crossed.
    Clamp,
    /// A uniform point between the parent's coordinate and the bound it crossed.
    BounceBack,
}

/// Stop once the best SSE gained less than `gain` (relative: best_after < best_before·(1 − gain)
/// fails) in `generations` generations in a row.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Stall {
    /// Relative gain below which a generation counts as stalled.
    pub gain: f64,
    /// Stalled generations in a row that stop the run.
    pub generations: usize,
}

/// The settings of one differential evolution (module doc).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Evolution {
    /// Weight F of both difference terms.
    pub weight: f64,
    /// Crossover probability CR (binomial, one coordinate j_rand always from the mutant); `None`:
    /// every coordinate from the mutant, and neither j_rand nor the per-coordinate draws are made.
    pub crossover: Option<f64>,
    /// Donors r1 ≠ i and r2 ∉ {i, r1} (drawn again until they are); else any two members.
    pub distinct_donors: bool,
    /// A mutant coordinate outside its bounds.
    pub boundary: Boundary,
    /// At most this many generations.
    pub generations: usize,
    /// Stop on a stalled best SSE.
    pub stall: Option<Stall>,
    /// Stop once the worst finite SSE is at most (1 + ε) times the best.
    pub spread: Option<f64>,
}

/// A population and each member's SSE.
#[derive(Debug, Clone, PartialEq)]
pub struct Population {
    /// The members (each a point inside the bounds).
    pub members: Vec<Vec<f64>>,
    /// Their SSE (same order).
    pub sse: Vec<f64>,
}

impl Population {
    /// The best member and its SSE (the first of equal ones).
    pub fn best(&self) -> (&[f64], f64) {
        let b = best_index(&self.sse);
        (&self.members[b], self.sse[b])
    }
}

impl Evolution {
    /// Evolves `population` inside `bounds`; `objective(θ, parent_sse)` is a trial's SSE (it may
    /// return any value above `parent_sse` once the sum passes it), `generation(population)` is
    /// called after each generation's selection (progress, traces). Returns the best member and
    /// its SSE.
    pub fn run(
        &self,
        mut population: Population,
        bounds: &[(f64, f64)],
        rng: &mut ChaCha8Rng,
        objective: impl Fn(&[f64], f64) -> f64 + Sync,
        mut generation: impl FnMut(&Population),
    ) -> (Vec<f64>, f64) {
        let pop = population.members.len();
        if pop == 0 {
            return (Vec::new(), f64::INFINITY);
        }
        let mut stalled = 0;
        for _ in 0..self.generations {
            let best = best_index(&population.sse);
            let trials: Vec<Vec<f64>> = (0..pop)
                .map(|i| self.trial(&population.members, i, best, bounds, rng))
                .collect();
            let f = &mut population.sse;
            let ft: Vec<f64> = trials
                .par_iter()
                .zip(f.par_iter())
                .map(|(t, &parent)| objective(t, parent))
                .collect();
            let before = f[best];
            for (i, (t, v)) in trials.into_iter().zip(ft).enumerate() {
                if v <= f[i] {
                    population.members[i] = t;
                    f[i] = v;
                }
            }
            let after = f.iter().copied().fold(f64::INFINITY, f64::min);
            let worst = f.iter().copied().fold(0.0f64, f64::max);
            generation(&population);
            if let Some(stall) = self.stall {
                stalled = if after < before * (1.0 - stall.gain) {
                    0
                } else {
                    stalled + 1
                };
                if stalled >= stall.generations {
                    break;
                }
            }
            if self
                .spread
                .is_some_and(|eps| worst.is_finite() && worst <= after * (1.0 + eps))
            {
                break;
            }
        }
        let (x, f) = population.best();
        (x.to_vec(), f)
    }

    /// The trial of member `i` (module doc): donors, mutant, crossover, bounds.
    fn trial(
        &self,
        x: &[Vec<f64>],
        i: usize,
        best: usize,
        bounds: &[(f64, f64)],
        rng: &mut ChaCha8Rng,
    ) -> Vec<f64> {
        let pop = x.len();
        let (mut r1, mut r2) = (index(rng, pop), index(rng, pop));
        // A population of one or two has no distinct donors: the draws would never end.
        if self.distinct_donors && pop > 2 {
            while r1 == i {
                r1 = index(rng, pop);
            }
            while r2 == i || r2 == r1 {
                r2 = index(rng, pop);
            }
        }
        let j_rand = self.crossover.map(|_| index(rng, bounds.len()));
        let f = self.weight;
        (0..bounds.len())
            .map(|j| {
                let (lo, hi) = bounds[j];
                let from_mutant = match self.crossover {
                    None => true,
                    Some(cr) => Some(j) == j_rand || uniform(rng) < cr,
                };
                if !from_mutant {
                    return x[i][j];
                }
                let v = x[i][j] + f * (x[best][j] - x[i][j]) + f * (x[r1][j] - x[r2][j]);
                match self.boundary {
                    Boundary::Clamp => v.clamp(lo, hi),
                    Boundary::BounceBack if v < lo => lo + (x[i][j] - lo) * uniform(rng),
                    Boundary::BounceBack if v > hi => hi - (hi - x[i][j]) * uniform(rng),
                    Boundary::BounceBack => v,
                }
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand_core::SeedableRng;

    const BOUNDS: [(f64, f64); 3] = [(-5.0, 5.0), (-5.0, 5.0), (0.0, 3.0)];

    /// (x − 1)² + (y + 2)² + (z − 2.5)², minimum 0 at (1, −2, 2.5).
    fn bowl(x: &[f64]) -> f64 {
        (x[0] - 1.0).powi(2) + (x[1] + 2.0).powi(2) + (x[2] - 2.5).powi(2)
    }

    fn run(settings: Evolution, seed: u64, size: usize) -> ((Vec<f64>, f64), usize) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let members = random_population(&BOUNDS, size, &mut rng);
        let sse = members.iter().map(|m| bowl(m)).collect();
        let mut generations = 0;
        let best = settings.run(
            Population { members, sse },
            &BOUNDS,
            &mut rng,
            |x, _| bowl(x),
            |p| {
                generations += 1;
                assert!(p.members.iter().flatten().all(|v| v.is_finite()));
            },
        );
        (best, generations)
    }

    fn settings() -> Evolution {
        Evolution {
            weight: 0.6,
            crossover: Some(0.9),
            distinct_donors: true,
            boundary: Boundary::BounceBack,
            generations: 200,
            stall: None,
            spread: None,
        }
    }

    #[test]
    fn finds_the_minimum_of_a_bowl_inside_the_bounds_in_every_variant() {
        for (crossover, distinct_donors, boundary) in [
            (Some(0.9), true, Boundary::BounceBack),
            (Some(0.9), false, Boundary::Clamp),
            (None, false, Boundary::Clamp),
        ] {
            let s = Evolution {
                crossover,
                distinct_donors,
                boundary,
                ..settings()
            };
            let ((x, f), _) = run(s, 3, 20);
            assert!(f < 1e-8, "{s:?}: {x:?} {f:e}");
            for (v, (lo, hi)) in x.iter().zip(BOUNDS) {
                assert!((lo..=hi).contains(v));
            }
        }
    }

    #[test]
    fn a_seed_gives_the_same_run_and_another_seed_another() {
        // Three generations: far from converged, so the runs still differ by seed.
        let short = Evolution {
            generations: 3,
            ..settings()
        };
        assert_eq!(run(short, 5, 15), run(short, 5, 15));
        assert_ne!(run(short, 5, 15).0 .0, run(short, 6, 15).0 .0);
    }

    #[test]
    fn the_stopping_rules_end_the_run() {
        let stall = Evolution {
            stall: Some(Stall {
                gain: 1e-4,
                generations: 5,
            }),
            ..settings()
        };
        let (_, stalled) = run(stall, 1, 15);
        assert!(stalled < 200, "{stalled}");
        let spread = Evolution {
            spread: Some(1e-3),
            ..settings()
        };
        let (_, collapsed) = run(spread, 1, 15);
        assert!(collapsed < 200, "{collapsed}");
        assert_eq!(run(settings(), 1, 15).1, 200);
    }

    #[test]
    fn a_population_too_small_for_distinct_donors_still_evolves() {
        // Two members have no r1 ≠ i and r2 ∉ {i, r1}: drawing until they are would never end.
        let ((_, f), generations) = run(settings(), 2, 2);
        assert_eq!(generations, 200);
        assert!(f.is_finite());
    }
}
