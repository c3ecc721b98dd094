//! The dense linear solver of every fit in host-sim: Gaussian elimination with partial pivoting on
//! an augmented system `[A | b]` (n rows of n + 1 entries), then back substitution.
//!
//! Forward elimination, for each column c: pick the row p ≥ c with the largest |a_pc| (the first
//! of equal ones), swap it into row c, and subtract f = a_rc/a_cc times row c from every row r > c.
//! Back substitution: x_r = (b_r − Σ_{k>r} a_rk·x_k)/a_rr from the last row up. A pivot below
//! 1e-300 in magnitude or not finite makes the system singular (no solution), and so does a
//! solution that is not finite. Golub & Van Loan, *Matrix Computations*, 4th ed., §3.4
//! (Gaussian elimination with partial pivoting).
//!
//! The rows may be stack arrays or vectors, so that a small system is solved without a heap
//! allocation (the identification's per-evaluation 3×3 projection).

/// Solves the augmented system `a` (n rows `[a_r0 … a_r(n−1) | b_r]`, n = `x.len()`, each row at
/// least n + 1 long) in place and writes the solution into `x`. Returns whether the system was
/// regular and the solution finite (`x` is then meaningful); `a` is overwritten either way.
pub fn solve_augmented<R: AsRef<[f64]> + AsMut<[f64]>>(a: &mut [R], x: &mut [f64]) -> bool {
    let n = x.len();
    if a.len() < n || a[..n].iter().any(|row| row.as_ref().len() <= n) {
        return false;
    }
    for c in 0..n {
        let Some(p) =
            (c..n).max_by(|&i, &j| a[i].as_ref()[c].abs().total_cmp(&a[j].as_ref()[c].abs()))
        else {
            return false;
        };
        let pivot = a[p].as_ref()[c];
        if pivot.abs() < 1e-300 || !pivot.is_finite() {
            return false;
        }
        a.swap(c, p);
        for r in c + 1..n {
            let (upper, lower) = a.split_at_mut(r);
            let (top, row) = (upper[c].as_ref(), lower[0].as_mut());
            let f = row[c] / top[c];
            for k in c..=n {
                row[k] -= f * top[k];
            }
        }
    }
    for r in (0..n).rev() {
        let row = a[r].as_ref();
        let s: f64 = (r + 1..n).map(|k| row[k] * x[k]).sum();
        x[r] = (row[n] - s) / row[r];
    }
    x.iter().all(|v| v.is_finite())
}

/// Solves the first `n` rows of the augmented system `a` (n×(n+1), see [`solve_augmented`]);
/// `None` when it is singular or the solution is not finite.
pub fn solve(a: &mut [Vec<f64>], n: usize) -> Option<Vec<f64>> {
    let mut x = vec![0.0; n];
    let rows = a.get_mut(..n)?;
    solve_augmented(rows, &mut x).then_some(x)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn solves_a_system_that_needs_a_row_swap() {
        // a_00 = 0: without pivoting the first step divides by zero.
        let mut a = vec![
            vec![0.0, 2.0, 1.0, 7.0],
            vec![1.0, 1.0, 1.0, 6.0],
            vec![2.0, 1.0, 3.0, 13.0],
        ];
        let x = solve(&mut a, 3).expect("regular");
        for (got, want) in x.iter().zip([1.0, 2.0, 3.0]) {
            assert!((got - want).abs() < 1e-12, "{x:?}");
        }
    }

    #[test]
    fn a_singular_system_has_no_solution() {
        let mut a = vec![vec![1.0, 2.0, 3.0], vec![2.0, 4.0, 6.0]];
        assert!(solve(&mut a, 2).is_none());
        let mut nan = [[f64::NAN, 1.0], [0.0, 0.0]];
        assert!(!solve_augmented(&mut nan[..1], &mut [0.0]));
    }

    #[test]
    fn stack_rows_give_the_same_numbers_as_vectors() {
        let rows = [
            [4.0, 1.0, 0.5, 1.0],
            [1.0, 3.0, 0.2, 2.0],
            [0.5, 0.2, 2.0, 3.0],
        ];
        let mut stack = rows;
        let mut x = [0.0; 3];
        assert!(solve_augmented(&mut stack, &mut x));
        let mut heap: Vec<Vec<f64>> = rows.iter().map(|r| r.to_vec()).collect();
        assert_eq!(solve(&mut heap, 3).expect("regular"), x.to_vec());
    }

    #[test]
    fn rows_too_short_for_the_unknowns_are_refused() {
        let mut a = vec![vec![1.0, 2.0]];
        assert!(solve(&mut a, 2).is_none());
        let mut short = [[1.0, 2.0]];
        assert!(!solve_augmented(&mut short, &mut [0.0, 0.0]));
    }
}
