//! The numerical engine of host-sim's fits: one differential evolution ([`evolution`]), one
//! Levenberg–Marquardt over a problem trait ([`marquardt`]) and one dense linear solver
//! ([`linear`]). `identify` (the static and dynamic models, and the Bouc-Wen benchmark
//! oscillator), `close-loop`'s refit of a whole axis model and the servo bench's mode fit all call
//! these; each caller keeps its own settings (population, weights, damping, stopping rules), so
//! its fits are the numbers they were, and a fix here reaches every fit at once.
//!
//! - Differential evolution, current-to-best/1 with binomial crossover (Storn & Price 1997):
//!   v = x_i + F·(x_best − x_i) + F·(x_r1 − x_r2), greedy selection t ≤ x; stops on a generation
//!   cap, a stalled best or a collapsed population.
//! - Levenberg–Marquardt (Marquardt 1963): (JᵀJ + λ·diag JᵀJ)·d = −Jᵀr, accepted when the SSE
//!   falls (λ/3), else λ·4; the caller supplies JᵀJ and Jᵀr; stops when no step helps, on small
//!   gains, or when the linear model promises too little.
//! - Gaussian elimination with partial pivoting (Golub & Van Loan §3.4) on an augmented system,
//!   on the stack or the heap.

pub mod evolution;
pub mod linear;
pub mod marquardt;

pub use evolution::{Boundary, Evolution, Population, Stall};
pub use marquardt::{LeastSquares, Marquardt, NormalEquations};
