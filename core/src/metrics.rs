//! Error measures of the seeds, as slice functions (accumulated in f64).
//!
//! With measured `x`, predicted `x̂`, error `e = x̂ − x` (prediction minus measurement) and `N` samples:
//!
//! ```text
//! SSE = Σ (x − x̂)²                 SST = Σ (x − x̄)²                 R² = 1 − SSE/SST   (seed 000 eq. 29–31)
//! MRD = max|x − x̂| / max|x| · 100 %                                                   (seed 000 eq. 32)
//! RMS = √(SSE/N)        (seed 001's fitness and "average fitness value", AFV, eq. 4)
//! RAE = [min e, max e]  (seed 001's "range of absolute error")
//! ```
//!
//! MRD is printed in seed 000 with `max x` in the denominator; this uses `max|x|`, which is the same for
//! the paper's positive displacements and stays meaningful for signed data.
//!
//! Every function returns `None` when the slices are empty or of different lengths (and, for R²,
//! when SST = 0; for MRD, when max|x| = 0).

/// Σ (x − x̂)².
pub fn sse<T: Copy + Into<f64>>(measured: &[T], predicted: &[T]) -> Option<f64> {
    pairs(measured, predicted).map(|it| it.map(|(x, p)| (x - p) * (x - p)).sum())
}

/// Σ (x − x̄)².
pub fn sst<T: Copy + Into<f64>>(measured: &[T]) -> Option<f64> {
    if measured.is_empty() {
        return None;
    }
    let n = measured.len() as f64;
    let mean = measured.iter().map(|&x| x.into()).sum::<f64>() / n;
    Some(
        measured
            .iter()
            .map(|&x| {
                let d = x.into() - mean;
                d * d
            })
            .sum(),
    )
}

/// R² = 1 − SSE/SST.
pub fn r_squared<T: Copy + Into<f64>>(measured: &[T], predicted: &[T]) -> Option<f64> {
    let total = sst(measured)?;
    if total == 0.0 {
        return None;
    }
    Some(1.0 - sse(measured, predicted)? / total)
}

/// MRD = max|x − x̂| / max|x| · 100 \[%\].
pub fn mrd_percent<T: Copy + Into<f64>>(measured: &[T], predicted: &[T]) -> Option<f64> {
    let worst = pairs(measured, predicted)?.fold(0.0f64, |m, (x, p)| m.max((x - p).abs()));
    let scale = measured.iter().fold(0.0f64, |m, &x| m.max(x.into().abs()));
    if scale == 0.0 {
        return None;
    }
    Some(worst / scale * 100.0)
}

/// RMS = √(SSE/N) (seed 001's fitness, AFV).
pub fn rms<T: Copy + Into<f64>>(measured: &[T], predicted: &[T]) -> Option<f64> {
    Some(libm::sqrt(
        sse(measured, predicted)? / measured.len() as f64,
    ))
}

/// RAE = (min e, max e) with e = x̂ − x.
pub fn rae<T: Copy + Into<f64>>(measured: &[T], predicted: &[T]) -> Option<(f64, f64)> {
    pairs(measured, predicted).map(|it| {
        it.fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), (x, p)| {
            (lo.min(p - x), hi.max(p - x))
        })
    })
}

fn pairs<'a, T: Copy + Into<f64>>(
    measured: &'a [T],
    predicted: &'a [T],
) -> Option<impl Iterator<Item = (f64, f64)> + 'a> {
    if measured.is_empty() || measured.len() != predicted.len() {
        return None;
    }
    Some(
        measured
            .iter()
            .zip(predicted)
            .map(|(&x, &p)| (x.into(), p.into())),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hand_computed_values() {
        let x = [1.0f64, 2.0, 3.0, 4.0];
        let p = [1.5f64, 2.0, 2.0, 4.0];
        assert_eq!(sse(&x, &p), Some(1.25));
        assert_eq!(sst(&x), Some(5.0));
        assert_eq!(r_squared(&x, &p), Some(0.75));
        assert_eq!(mrd_percent(&x, &p), Some(25.0));
        assert_eq!(rms(&x, &p), Some((1.25f64 / 4.0).sqrt()));
        assert_eq!(rae(&x, &p), Some((-1.0, 0.5)));
    }

    #[test]
    fn mismatched_or_degenerate_inputs_give_none() {
        let x = [1.0f32, 2.0];
        assert_eq!(sse(&x, &[1.0f32]), None);
        assert_eq!(rms::<f32>(&[], &[]), None);
        assert_eq!(r_squared(&[2.0f32, 2.0], &[2.0, 2.0]), None);
        assert_eq!(mrd_percent(&[0.0f32, 0.0], &[1.0, 1.0]), None);
    }
}
