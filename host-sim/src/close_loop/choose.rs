//! Which screened candidates are fitted, and why each of the others is not.
//!
//! The screening ([`super::diagnose`]) regresses the residual on one signature per effect. On a
//! periodic record four of them are close to collinear: a lag of u (creep), a lag of the
//! hysteresis state h (rate-dependent hysteresis), the prediction delayed by D (delay) and a
//! mode above the band (dynamics) each shift the output's phase at the excitation frequency by a
//! small angle, so the residual of a base model that lacks any one of them looks like the others'
//! signature too, and their screening shares do not say which it is ([`PHASE_EFFECTS`]). Hence:
//!
//! 1. the effects whose best form's share is at least `needed` are fitted, best first, up to
//!    [`super::MAX_TRIALS`] effects, each in every form whose share is at least `needed`: the
//!    screening ranks effects, and which form an effect takes (Kelvin–Voigt or logarithmic creep,
//!    linear or settling drift) is the fit's and the held-out test's to say;
//! 2. when one of the fitted candidates is a phase effect, every other phase effect the search may
//!    still add is fitted as well (its best form): the screening cannot separate them, the fit and
//!    the held-out test do;
//! 3. every other effect is reported with why it was not fitted ([`NotTried`]): another form of
//!    it was fitted, its share is below `needed`, it ranked below the first
//!    [`super::MAX_TRIALS`], or it was not screened (already in the model, not allowed, no other
//!    axis to couple to).

use super::diagnose::{Candidate, EffectKind};

/// The effects the screening cannot tell apart on a periodic record (module doc).
pub const PHASE_EFFECTS: [EffectKind; 4] = [
    EffectKind::Creep,
    EffectKind::Delay,
    EffectKind::RateDependent,
    EffectKind::Dynamics,
];

/// Why a candidate is fitted.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Tried {
    /// Among the best by screening share.
    Ranked,
    /// A phase effect the screening cannot separate from this one, which was fitted.
    Inseparable(EffectKind),
}

/// Why an effect is not fitted in a step (serialised as [`NotTried::name`]).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
#[serde(into = "&'static str")]
pub enum NotTried {
    /// Another form of the effect, with a larger share, is fitted (this one's share is below
    /// the share needed).
    OtherForm,
    /// Its screening share is below the share a candidate needs.
    BelowShare {
        /// The share needed.
        needed: f64,
    },
    /// It ranked below the first [`super::MAX_TRIALS`] and is not a phase effect of one fitted.
    Ranked {
        /// Its effect's rank among the effects with the share needed (from 1).
        rank: usize,
    },
    /// It is in the model already.
    InModel,
    /// The run's settings do not allow it.
    NotAllowed,
    /// Coupling needs the other axis's record.
    NoOtherAxis,
    /// Its screening found no start (too few samples for its grid).
    NoScreening,
}

impl NotTried {
    /// In words.
    pub fn words(self) -> String {
        match self {
            Self::OtherForm => {
                "another form of it, with a larger screening share, is fitted".into()
            }
            Self::BelowShare { needed } => format!(
                "its screening share is below the {:.2} % a candidate needs",
                100.0 * needed
            ),
            Self::Ranked { rank } => format!(
                "ranked {rank} by screening share, below the first {}, and not an effect the \
                 screening cannot separate from one fitted",
                super::MAX_TRIALS
            ),
            Self::InModel => "it is in the model already".into(),
            Self::NotAllowed => "the run's settings do not allow it".into(),
            Self::NoOtherAxis => "coupling needs the other axis's record".into(),
            Self::NoScreening => "its screening found no start".into(),
        }
    }

    /// Short name for the report.
    pub fn name(self) -> &'static str {
        match self {
            Self::OtherForm => "other-form-fitted",
            Self::BelowShare { .. } => "below-share",
            Self::Ranked { .. } => "ranked-below",
            Self::InModel => "in-model",
            Self::NotAllowed => "not-allowed",
            Self::NoOtherAxis => "no-other-axis",
            Self::NoScreening => "no-screening",
        }
    }
}

impl From<NotTried> for &'static str {
    fn from(reason: NotTried) -> Self {
        reason.name()
    }
}

/// An effect (or a form of it) not fitted in a step, and why.
#[derive(Debug, Clone, PartialEq)]
pub struct Skipped {
    /// The effect.
    pub effect: EffectKind,
    /// The form screened ("" when not screened).
    pub form: &'static str,
    /// Its screening share (None when not screened).
    pub share: Option<f64>,
    /// Why.
    pub reason: NotTried,
}

impl Skipped {
    /// In words.
    pub fn words(&self) -> String {
        let label = if self.form.is_empty() {
            self.effect.name().to_string()
        } else {
            format!("{} ({})", self.effect.name(), self.form)
        };
        match self.share {
            Some(s) => format!(
                "{label}: not fitted (screening {:.1} %): {}",
                100.0 * s,
                self.reason.words()
            ),
            None => format!("{label}: not fitted: {}", self.reason.words()),
        }
    }

    /// For the report, with its words.
    pub fn report(&self) -> SkippedReport {
        SkippedReport {
            effect: self.effect,
            form: self.form,
            share: self.share,
            reason: self.reason,
            words: self.words(),
        }
    }
}

/// An effect not fitted in a report ([`Skipped::report`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct SkippedReport {
    /// The effect.
    pub effect: EffectKind,
    /// The form screened ("" when not screened).
    pub form: &'static str,
    /// Its screening share (null when not screened).
    pub share: Option<f64>,
    /// Why ([`NotTried::name`]).
    pub reason: NotTried,
    /// In words ([`Skipped::words`]).
    pub words: String,
}

/// The candidates (indices into `candidates`, best first by share) that are fitted, with why,
/// and the others with why not (module doc). `needed`: the smallest screening share fitted;
/// `max_ranked`: how many are fitted by rank.
pub fn choose(
    candidates: &[Candidate],
    needed: f64,
    max_ranked: usize,
) -> (Vec<(usize, Tried)>, Vec<Skipped>) {
    // The effects with the share needed, best first (their rank), and those fitted by rank.
    let mut ranks: Vec<EffectKind> = Vec::new();
    for c in candidates.iter().filter(|c| c.share >= needed) {
        if !ranks.contains(&c.effect) {
            ranks.push(c.effect);
        }
    }
    let rank_of = |e: EffectKind| ranks.iter().position(|r| *r == e).map(|p| p + 1);
    let mut tried: Vec<(usize, Tried)> = candidates
        .iter()
        .enumerate()
        .filter(|(_, c)| c.share >= needed && rank_of(c.effect).is_some_and(|r| r <= max_ranked))
        .map(|(i, _)| (i, Tried::Ranked))
        .collect();
    let first_phase = tried
        .iter()
        .map(|&(i, _)| candidates[i].effect)
        .find(|e| PHASE_EFFECTS.contains(e));
    if let Some(fitted) = first_phase {
        for effect in PHASE_EFFECTS {
            if tried.iter().any(|&(i, _)| candidates[i].effect == effect) {
                continue;
            }
            // The effect's best form (the candidates are sorted by share).
            if let Some(i) = candidates.iter().position(|c| c.effect == effect) {
                tried.push((i, Tried::Inseparable(fitted)));
            }
        }
    }
    let mut skipped = Vec::new();
    for (i, c) in candidates.iter().enumerate() {
        if tried.iter().any(|&(j, _)| j == i) {
            continue;
        }
        let reason = if tried.iter().any(|&(j, _)| candidates[j].effect == c.effect) {
            NotTried::OtherForm
        } else {
            match rank_of(c.effect) {
                Some(rank) if c.share >= needed => NotTried::Ranked { rank },
                _ => NotTried::BelowShare { needed },
            }
        };
        skipped.push(Skipped {
            effect: c.effect,
            form: c.init.form(),
            share: Some(c.share),
            reason,
        });
    }
    (tried, skipped)
}

/// The effects not screened in a step and why: in `model_added`, not in `allowed`, coupling
/// without the other axis, or screened without a start (absent from `candidates`).
pub fn not_screened(
    allowed: &[EffectKind],
    model_added: &[EffectKind],
    has_other_axis: bool,
    candidates: &[Candidate],
) -> Vec<Skipped> {
    EffectKind::ALL
        .iter()
        .filter(|e| !candidates.iter().any(|c| c.effect == **e))
        .map(|&effect| Skipped {
            effect,
            form: "",
            share: None,
            reason: if model_added.contains(&effect) {
                NotTried::InModel
            } else if !allowed.contains(&effect) {
                NotTried::NotAllowed
            } else if effect == EffectKind::Coupling && !has_other_axis {
                NotTried::NoOtherAxis
            } else {
                NotTried::NoScreening
            },
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::close_loop::diagnose::EffectInit;

    /// An effect not fitted serialises with the keys of the report: its name, form, share, the
    /// reason's short name and the words.
    #[test]
    fn a_skipped_effect_serialises_as_in_the_report() {
        let skipped = Skipped {
            effect: EffectKind::RateDependent,
            form: "relaxation",
            share: Some(0.01),
            reason: NotTried::BelowShare { needed: 0.05 },
        };
        let json = crate::to_json(&skipped.report()).unwrap();
        assert_eq!(
            json,
            serde_json::json!({
                "effect": "rate-dependent hysteresis",
                "form": "relaxation",
                "share": 0.01,
                "reason": "below-share",
                "words": skipped.words(),
            })
        );
        let unscreened = Skipped {
            form: "",
            share: None,
            reason: NotTried::NoScreening,
            ..skipped
        };
        let json = crate::to_json(&unscreened.report()).unwrap();
        assert!(json["share"].is_null());
        assert_eq!(json["reason"], "no-screening");
    }

    fn cand(effect: EffectKind, share: f64) -> Candidate {
        let init = match effect {
            EffectKind::Creep => EffectInit::LogCreep { gain_m_per_v: 1e-9 },
            EffectKind::Delay => EffectInit::Delay { delay_s: 1e-4 },
            EffectKind::Drift => EffectInit::Drift { rate_m_per_s: 1e-9 },
            EffectKind::Asymmetry => EffectInit::Asymmetry {
                coefficient_m_per_v2: 1e-12,
                center_v: 0.0,
            },
            EffectKind::Dynamics => EffectInit::Dynamics {
                frequency_hz: 1e3,
                damping: 0.1,
            },
            EffectKind::Coupling => EffectInit::Coupling { coefficient: 0.01 },
            EffectKind::RateDependent => EffectInit::RateDependent {
                lag_coefficient_m: 1e-7,
                time_constant_s: 1e-3,
            },
        };
        Candidate {
            effect,
            share,
            delta_bic: 0.0,
            init,
            test: "",
            figures: Vec::new(),
        }
    }

    #[test]
    fn a_phase_effect_fitted_brings_the_others_below_the_share() {
        // Creep first by screening; delay, rate-dependent hysteresis and dynamics explain nothing
        // on the screening yet are fitted; drift and asymmetry below the share are not.
        let c = [
            cand(EffectKind::Creep, 0.6),
            cand(EffectKind::Drift, 0.06),
            cand(EffectKind::Asymmetry, 0.001),
            cand(EffectKind::RateDependent, 0.0),
            cand(EffectKind::Delay, 0.0),
            cand(EffectKind::Dynamics, 0.0),
        ];
        let (tried, skipped) = choose(&c, 0.0125, 4);
        let fitted: Vec<EffectKind> = tried.iter().map(|&(i, _)| c[i].effect).collect();
        assert_eq!(
            fitted,
            [
                EffectKind::Creep,
                EffectKind::Drift,
                EffectKind::Delay,
                EffectKind::RateDependent,
                EffectKind::Dynamics
            ]
        );
        assert_eq!(tried[3].1, Tried::Inseparable(EffectKind::Creep));
        assert_eq!(skipped.len(), 1);
        assert_eq!(skipped[0].effect, EffectKind::Asymmetry);
        assert_eq!(skipped[0].reason, NotTried::BelowShare { needed: 0.0125 });
    }

    /// The ranks go to effects: a ranked effect's other forms with the share needed are fitted
    /// too, and an effect ranked below the first two is not, whatever its forms' shares.
    #[test]
    fn without_a_phase_effect_only_the_ranked_are_fitted() {
        let c = [
            cand(EffectKind::Drift, 0.5),
            cand(EffectKind::Asymmetry, 0.3),
            cand(EffectKind::Coupling, 0.2),
            cand(EffectKind::Drift, 0.1),
            cand(EffectKind::Drift, 0.001),
            cand(EffectKind::Delay, 0.0),
        ];
        let (tried, skipped) = choose(&c, 0.0125, 2);
        assert_eq!(
            tried,
            vec![(0, Tried::Ranked), (1, Tried::Ranked), (3, Tried::Ranked)]
        );
        let reasons: Vec<NotTried> = skipped.iter().map(|s| s.reason).collect();
        assert_eq!(
            reasons,
            [
                NotTried::Ranked { rank: 3 },
                NotTried::OtherForm,
                NotTried::BelowShare { needed: 0.0125 }
            ]
        );
    }

    #[test]
    fn effects_not_screened_say_why() {
        let c = [cand(EffectKind::Drift, 0.5)];
        let all = EffectKind::ALL;
        let s = not_screened(&all[..6], &[EffectKind::Creep], false, &c);
        let r = |e: EffectKind| s.iter().find(|x| x.effect == e).map(|x| x.reason);
        assert_eq!(r(EffectKind::Creep), Some(NotTried::InModel));
        assert_eq!(r(EffectKind::RateDependent), Some(NotTried::NotAllowed));
        assert_eq!(r(EffectKind::Coupling), Some(NotTried::NoOtherAxis));
        assert_eq!(r(EffectKind::Delay), Some(NotTried::NoScreening));
        assert_eq!(r(EffectKind::Drift), None);
    }
}
