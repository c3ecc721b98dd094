//! Reference generator: the two-axis setpoint of each tick, in the unit of the program's
//! request (metres for a tracked reference, stack volts for an excitation).
//!
//! Programs ([`Program`], piezo-core's, as the command link carries them):
//! - per axis a [`Wave`]: constant, sine, triangle or steps (square wave), each
//!   `offset + amplitude · w(φ)` with `w ∈ [−1, 1]` and a phase φ in cycles advanced by
//!   `f · T` per tick and wrapped to `[0, 1)` (no precision loss over long runs);
//! - a raster: x sweeps a triangle between `x_min` and `x_max`, one line per half period; at
//!   each turn-around y moves to the next of `lines` equally spaced rows between `y_min` and
//!   `y_max`, then back (boustrophedon in both directions);
//! - streamed setpoints: one `[x, y]` per tick from a fixed-capacity queue
//!   ([`STREAM_CAPACITY`] − 1 entries, `heapless::spsc::Queue`), filled by the host link; when
//!   the queue runs dry the last setpoint is held and the underrun is counted;
//! - a wave table of up to [`TABLE_CAPACITY`] `[x, y]` entries (16 KiB), filled by the host
//!   link: entry j at tick j·m, linear in between, then held at the last entry or started again;
//!   at m = 10 and 10 kHz it holds 2 s. The completed passes over a repeating table are counted
//!   ([`ReferenceGenerator::pass`]: the trial a tick belongs to);
//! - with the wave table, a *learned voltage table* of as many `[u_x, u_y]` stack voltages
//!   ([`ReferenceGenerator::learned_append`], another 16 KiB): entry j is the command for wave
//!   table entry j, played at the same ticks with the same interpolation,
//!   `u(t) = u[j] + (t − j·m)/m·(u[j+1] − u[j])` for `j·m ≤ t < (j+1)·m` (u\[j+1\] = u\[0\] after
//!   the last entry of a repeating table) ([`ReferenceGenerator::next_learned`]). It is checked
//!   before it is played ([`ReferenceGenerator::check_learned`]): its length is the wave table's,
//!   every entry finite and inside each axis's window, and every step between consecutive
//!   entries, `|u[j+1] − u[j]|`, at most `m·M` (M the output guard's step bound per tick, m the
//!   ticks per entry), including the wrap `|u[0] − u[n−1]|` of a repeating table; the first
//!   entry that fails is named.
//!
//! [`ReferenceGenerator::next_setpoint`] never panics and does not allocate. A non-finite setpoint is
//! passed on: the compensator holds its voltage for it and the safety guard counts it.

use heapless::spsc::Queue;
pub use piezo_core::{Program, Wave};

/// Queue size for streamed setpoints (holds one fewer).
pub const STREAM_CAPACITY: usize = 64;
/// Entries of the wave table.
pub const TABLE_CAPACITY: usize = 2048;

/// A [`Wave`]'s value at a phase φ as the generator plays it, `offset + amplitude · w(φ)`
/// (piezo-core's `program` module states w for each shape), with the f32 sine in cycles
/// [`sin_turns`].
pub trait WaveAt {
    /// Value at phase `phase` cycles (in `[0, 1)`).
    fn at(&self, phase: f32) -> f32;

    /// [`WaveAt::at`] for a phase already in \[0, 1) (the generator's wrapped phases): the
    /// sine without [`sin_turns`]' check for a non-finite phase, which such a phase never takes;
    /// the same bits as [`WaveAt::at`] there.
    fn at_wrapped(&self, phase: f32) -> f32;
}

impl WaveAt for Wave {
    #[inline(always)]
    fn at_wrapped(&self, phase: f32) -> f32 {
        match *self {
            Wave::Sine {
                offset, amplitude, ..
            } => offset + amplitude * sin_turns_finite(phase),
            _ => self.at(phase),
        }
    }

    #[inline(always)]
    fn at(&self, phase: f32) -> f32 {
        match *self {
            Wave::Constant { offset } => offset,
            Wave::Sine {
                offset, amplitude, ..
            } => offset + amplitude * sin_turns(phase),
            Wave::Triangle {
                offset, amplitude, ..
            } => offset + amplitude * triangle(phase),
            Wave::Steps {
                offset, amplitude, ..
            } => {
                if phase < 0.5 {
                    offset - amplitude
                } else {
                    offset + amplitude
                }
            }
        }
    }
}

/// sin(2π·φ) for φ in cycles, in f32 (libm's `sinf` computes in f64, which the Cortex-M4F
/// emulates in software: ≈ 690 instructions a call against ≈ 30 here). The quadrant
/// q = round(4φ) is taken in cycles, where the reduction `r = φ − q/4 ∈ [−⅛, ⅛]` is exact in f32
/// (Sterbenz), then x = 2π·r ∈ [−π/4, π/4] and, by q mod 4, ±sin x or ±cos x from Cephes' `sinf`
/// and `cosf` minimax polynomials:
/// `sin x ≈ x + x·z·(−1.6666654611e-1 + z·(8.3321608736e-3 − 1.9515295891e-4·z))`,
/// `cos x ≈ 1 − z/2 + z²·(4.166664568298827e-2 + z·(−1.388731625493765e-3 + 2.443315711809948e-5·z))`,
/// z = x². Within 1.2e-7 of sin(2πφ) for f32 φ in \[0, 1) (tested against f64; `libm::sinf(2π·φ)`
/// is off by up to 4.2e-7 through the rounding of the f32 product 2π·φ); NaN or ±∞
/// give NaN, a phase outside \[0, 1) is taken modulo 1 only through its quadrant (the generator
/// wraps its phases).
#[inline]
pub fn sin_turns(phase: f32) -> f32 {
    if !phase.is_finite() {
        return f32::NAN;
    }
    sin_turns_finite(phase)
}

/// [`sin_turns`] for a finite phase (the same bits; a non-finite one gives a finite value).
#[inline(always)]
fn sin_turns_finite(phase: f32) -> f32 {
    // round(4φ) for φ ≥ 0 (the generator's phases); saturating for anything else.
    let quadrant = (4.0 * phase + 0.5) as u32;
    let r = phase - quadrant as f32 * 0.25;
    let x = r * core::f32::consts::TAU;
    let z = x * x;
    let (value, negate) = match quadrant & 3 {
        0 | 2 => (
            x + x * z * (-1.666_665_5e-1 + z * (8.332_161e-3 - 1.951_529_6e-4 * z)),
            quadrant & 3 == 2,
        ),
        _ => (
            1.0 - 0.5 * z + z * z * (4.166_664_6e-2 + z * (-1.388_731_6e-3 + 2.443_315_7e-5 * z)),
            quadrant & 3 == 3,
        ),
    };
    if negate {
        -value
    } else {
        value
    }
}

/// −1 at 0, +1 at ½, −1 at 1.
fn triangle(phase: f32) -> f32 {
    if phase < 0.5 {
        4.0 * phase - 1.0
    } else {
        3.0 - 4.0 * phase
    }
}

/// The wave table cannot take the entries given.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TableFull {
    /// Entries it can still take.
    pub room: usize,
}

/// Appends all of `entries` to `table`, or none of them with the room left as the error.
fn append_all(
    table: &mut heapless::Vec<[f32; 2], TABLE_CAPACITY>,
    entries: &[[f32; 2]],
) -> Result<(), TableFull> {
    table.extend_from_slice(entries).map_err(|()| TableFull {
        room: TABLE_CAPACITY - table.len(),
    })
}

/// The generator: program, phase and the stream queue.
pub struct ReferenceGenerator {
    program: Program,
    sample_period_s: f32,
    phase: [f32; 2],
    /// Per tick, each phase's advance \[cycles\]: `f·T` per axis ([`Program::PerAxis`]), the
    /// raster's `(½·line_rate)·T` on x; the same products the tick would form, computed once when
    /// the program is set ([`phase_increments`]).
    increment: [f32; 2],
    /// Raster: completed lines since the start (wraps).
    line: u32,
    stream: Queue<[f32; 2], STREAM_CAPACITY>,
    last_streamed: [f32; 2],
    underruns: u32,
    table: heapless::Vec<[f32; 2], TABLE_CAPACITY>,
    /// Table: ticks since the program started (wrapped or held at the end).
    table_tick: u32,
    /// Table: passes completed before the entry of the last setpoint (wraps).
    pass: u32,
    /// Table: passes completed before the entry of the next setpoint (wraps).
    passes: u32,
    /// The learned voltage table \[V\], entry j for wave table entry j.
    learned: heapless::Vec<[f32; 2], TABLE_CAPACITY>,
}

/// Why the learned voltage table cannot be played (the first entry that fails).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum LearnedError {
    /// Its length is not the wave table's (or both are empty).
    Length {
        /// Learned entries held.
        learned: usize,
        /// Wave table entries held.
        wave: usize,
    },
    /// An entry is NaN or infinite.
    NotFinite {
        /// Entry index.
        entry: usize,
        /// 0 for x, 1 for y.
        axis: usize,
    },
    /// An entry is outside the axis's output window.
    Window {
        /// Entry index.
        entry: usize,
        /// 0 for x, 1 for y.
        axis: usize,
        /// The entry \[V\].
        value_v: f32,
        /// The window \[V\].
        window_v: [f32; 2],
    },
    /// The step into an entry exceeds the slew limit at the entry spacing.
    Slew {
        /// Entry index the step leads to (0: the wrap from the last entry).
        entry: usize,
        /// 0 for x, 1 for y.
        axis: usize,
        /// `|u[entry] − u[entry − 1]|` \[V\].
        step_v: f32,
        /// The bound m·M \[V\].
        limit_v: f32,
        /// Ticks per entry m.
        ticks_per_entry: u32,
    },
}

/// One axis's limits as [`ReferenceGenerator::check_learned`] reads them.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LearnedLimits {
    /// Output window \[V\].
    pub window_v: [f32; 2],
    /// The largest step per tick the output guard lets through, M \[V\].
    pub max_step_v: f32,
}

impl ReferenceGenerator {
    /// A generator for `program` at the loop period `sample_period_s`, starting at phase 0.
    /// `initial_m` is what [`Program::Streamed`] holds before the first setpoint arrives.
    pub fn new(program: Program, sample_period_s: f32, initial_m: [f32; 2]) -> Self {
        Self {
            program,
            sample_period_s,
            phase: [0.0; 2],
            increment: phase_increments(&program, sample_period_s),
            line: 0,
            stream: Queue::new(),
            last_streamed: initial_m,
            underruns: 0,
            table: heapless::Vec::new(),
            table_tick: 0,
            pass: 0,
            passes: 0,
            learned: heapless::Vec::new(),
        }
    }

    /// Empties the learned voltage table.
    pub fn learned_clear(&mut self) {
        self.learned.clear();
    }

    /// Appends `[u_x, u_y]` entries \[V\] to the learned voltage table; if they do not all fit,
    /// nothing is appended and `Err` gives the room left.
    pub fn learned_append(&mut self, entries: &[[f32; 2]]) -> Result<(), TableFull> {
        append_all(&mut self.learned, entries)
    }

    /// Learned voltage table entries held.
    pub fn learned_len(&self) -> usize {
        self.learned.len()
    }

    /// Checks the learned voltage table for playing with the wave table at `ticks_per_entry`
    /// (0 is taken as 1; see the module docs): the same length as the wave table, each entry
    /// finite and inside `limits[axis].window_v`, each step at most `m · max_step_v` (compared
    /// in f64, exact for f32 operands), the wrap too when `repeat`. Names the first entry that
    /// fails, entries in order, x before y.
    pub fn check_learned(
        &self,
        ticks_per_entry: u32,
        repeat: bool,
        limits: &[LearnedLimits; 2],
    ) -> Result<(), LearnedError> {
        let n = self.learned.len();
        if n == 0 || n != self.table.len() {
            return Err(LearnedError::Length {
                learned: n,
                wave: self.table.len(),
            });
        }
        let m = ticks_per_entry.max(1);
        for (entry, u) in self.learned.iter().enumerate() {
            for (axis, (&v, l)) in u.iter().zip(limits).enumerate() {
                if !v.is_finite() {
                    return Err(LearnedError::NotFinite { entry, axis });
                }
                if !(v >= l.window_v[0] && v <= l.window_v[1]) {
                    return Err(LearnedError::Window {
                        entry,
                        axis,
                        value_v: v,
                        window_v: l.window_v,
                    });
                }
            }
        }
        let steps = (1..n).chain(repeat.then_some(0));
        for entry in steps {
            let before = self.learned[(entry + n - 1) % n];
            let now = self.learned[entry];
            for (axis, l) in limits.iter().enumerate() {
                let step = (f64::from(now[axis]) - f64::from(before[axis])).abs();
                let limit = f64::from(m) * f64::from(l.max_step_v);
                // Finite: every entry was checked above.
                if step > limit {
                    return Err(LearnedError::Slew {
                        entry,
                        axis,
                        step_v: step as f32,
                        limit_v: limit as f32,
                        ticks_per_entry: m,
                    });
                }
            }
        }
        Ok(())
    }

    /// Passes completed over a repeating wave table before the entry of the last setpoint
    /// (0 since [`ReferenceGenerator::set_program`]; 0 for the other programs; wraps).
    pub fn pass(&self) -> u32 {
        self.pass
    }

    /// Empties the wave table.
    pub fn table_clear(&mut self) {
        self.table.clear();
    }

    /// Appends entries to the wave table; if they do not all fit, nothing is appended and
    /// `Err` gives the room left.
    pub fn table_append(&mut self, entries: &[[f32; 2]]) -> Result<(), TableFull> {
        append_all(&mut self.table, entries)
    }

    /// Wave table entries held.
    pub fn table_len(&self) -> usize {
        self.table.len()
    }

    /// The table's value `tick` ticks after its start.
    #[inline(always)]
    fn table_at(&self, tick: u32, ticks_per_entry: u32) -> [f32; 2] {
        interpolate(&self.table, tick, ticks_per_entry).unwrap_or(self.last_streamed)
    }

    /// The program.
    pub fn program(&self) -> Program {
        self.program
    }

    /// Switches program, restarting its phase (the stream queue is kept).
    pub fn set_program(&mut self, program: Program) {
        self.program = program;
        self.increment = phase_increments(&program, self.sample_period_s);
        self.phase = [0.0; 2];
        self.line = 0;
        self.table_tick = 0;
        self.pass = 0;
        self.passes = 0;
    }

    /// Queues one streamed setpoint; gives it back if the queue is full.
    pub fn push_setpoint(&mut self, setpoint_m: [f32; 2]) -> Result<(), [f32; 2]> {
        self.stream.enqueue(setpoint_m)
    }

    /// Streamed setpoints waiting.
    pub fn queued(&self) -> usize {
        self.stream.len()
    }

    /// Ticks in [`Program::Streamed`] that found the queue empty (saturating).
    pub fn underruns(&self) -> u32 {
        self.underruns
    }

    /// The setpoint of this tick, then advances one tick. Out of line: the tick calls it once,
    /// and its fields (program, phases, increments) are then read from the generator's own
    /// address instead of being held across the tick (`firmware/bench.sh`, 50 kHz stage file:
    /// worst feedforward + feedback tick 1757 → 1755 instructions, the whole tick 1373 → 1362
    /// on average). The per-axis waveforms are evaluated here; the other programs further out
    /// of line.
    #[inline(never)]
    pub fn next_setpoint(&mut self) -> [f32; 2] {
        if let Program::PerAxis([wx, wy]) = self.program {
            let [px, py] = self.phase;
            // The phases are wrapped into [0, 1) (finite) from the start: `at_wrapped`.
            let out = [wx.at_wrapped(px), wy.at_wrapped(py)];
            let [ix, iy] = self.increment;
            self.phase = [wrap(px + ix), wrap(py + iy)];
            out
        } else {
            self.next_setpoint_other()
        }
    }

    /// [`Self::next_setpoint`] for the programs other than [`Program::PerAxis`].
    #[inline(never)]
    fn next_setpoint_other(&mut self) -> [f32; 2] {
        match self.program {
            Program::PerAxis([wx, wy]) => {
                let [px, py] = self.phase;
                let out = [wx.at(px), wy.at(py)];
                let [ix, iy] = self.increment;
                self.phase = [wrap(px + ix), wrap(py + iy)];
                out
            }
            Program::Raster {
                x_min,
                x_max,
                y_min,
                y_max,
                lines,
                ..
            } => {
                let half = 0.5 * (x_max - x_min);
                let x = x_min + half + half * triangle(self.phase[0]);
                let rows = u32::from(lines.max(2));
                let k = self.line % (2 * rows - 2);
                let row = if k < rows { k } else { 2 * rows - 2 - k };
                let y = y_min + (y_max - y_min) * row as f32 / (rows - 1) as f32;
                let advanced = self.phase[0] + self.increment[0];
                // A line ends at each half period of the triangle.
                let before = self.phase[0] < 0.5;
                let wrapped = wrap(advanced);
                if (before && wrapped >= 0.5) || wrapped < self.phase[0] {
                    self.line = self.line.wrapping_add(1);
                }
                self.phase[0] = wrapped;
                [x, y]
            }
            Program::Table {
                ticks_per_entry,
                repeat,
            } => {
                let out = self.table_at(self.table_tick, ticks_per_entry);
                self.advance_table(ticks_per_entry, repeat);
                out
            }
            Program::Streamed => {
                match self.stream.dequeue() {
                    Some(s) => self.last_streamed = s,
                    None => self.underruns = self.underruns.saturating_add(1),
                }
                self.last_streamed
            }
        }
    }
}

impl ReferenceGenerator {
    /// One tick on: the wave table's position, and the pass when a repeating table starts
    /// again.
    #[inline(always)]
    fn advance_table(&mut self, ticks_per_entry: u32, repeat: bool) {
        let m = ticks_per_entry.max(1);
        let length = u32::try_from(self.table.len()).unwrap_or(u32::MAX);
        let next = self.table_tick.saturating_add(1);
        self.pass = self.passes;
        self.table_tick = if repeat {
            if next >= length.saturating_mul(m) {
                self.passes = self.passes.wrapping_add(1);
                0
            } else {
                next
            }
        } else {
            next.min(length.saturating_sub(1).saturating_mul(m))
        };
    }

    /// The setpoint of this tick and the learned voltage table's command for it \[V\], then
    /// advances one tick. With a table program both come from the same position (module docs);
    /// with any other program, or an empty learned table, the command is NaN (the output guard
    /// holds the voltage for it). Never panics.
    pub fn next_learned(&mut self) -> ([f32; 2], [f32; 2]) {
        match self.program {
            Program::Table {
                ticks_per_entry,
                repeat,
            } => {
                let tick = self.table_tick;
                let out = self.table_at(tick, ticks_per_entry);
                let u = interpolate(&self.learned, tick, ticks_per_entry).unwrap_or([f32::NAN; 2]);
                self.advance_table(ticks_per_entry, repeat);
                (out, u)
            }
            _ => (self.next_setpoint(), [f32::NAN; 2]),
        }
    }
}

/// Each phase's advance per tick \[cycles\] under `program` at the period `sample_period_s`:
/// `[f_x·T, f_y·T]` for [`Program::PerAxis`] (0 for a constant), `[(½·line_rate)·T, 0]` for a
/// raster, zeros otherwise. The tick adds these to its phases, so they are the products it
/// formed itself, bit for bit.
fn phase_increments(program: &Program, sample_period_s: f32) -> [f32; 2] {
    match *program {
        Program::PerAxis([wx, wy]) => [
            wx.frequency_hz() * sample_period_s,
            wy.frequency_hz() * sample_period_s,
        ],
        Program::Raster { line_rate_hz, .. } => [0.5 * line_rate_hz * sample_period_s, 0.0],
        Program::Streamed | Program::Table { .. } => [0.0; 2],
    }
}

/// `table`'s value `tick` ticks after its start at `ticks_per_entry` (0 taken as 1): entry j at
/// tick j·m, linear towards the next (the first after the last), the last entry beyond the end;
/// `None` for an empty table.
#[inline(always)]
fn interpolate(table: &[[f32; 2]], tick: u32, ticks_per_entry: u32) -> Option<[f32; 2]> {
    let m = ticks_per_entry.max(1);
    let (j, within) = ((tick / m) as usize, tick % m);
    let Some(&a) = table.get(j) else {
        return table.last().copied();
    };
    let b = match table.get(j + 1) {
        Some(&b) => b,
        None => table.first().copied().unwrap_or(a),
    };
    let f = within as f32 / m as f32;
    Some([a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1])])
}

/// Phase into `[0, 1)`; non-finite phases restart at 0. `phase − ⌊phase⌋`: a phase in (0, 1)
/// is itself and one in \[1, 2) (a phase advanced by less than a cycle) is `phase − 1` (exact),
/// without libm's `floorf`; the same bits as the general form below.
#[inline]
fn wrap(phase: f32) -> f32 {
    // 0 < phase < 1 on the bits: the positive f32 below 1.0 are the bit patterns
    // 1 ..= 0x3F7F_FFFF (one integer compare instead of two float ones).
    if phase.to_bits().wrapping_sub(1) < 0x3F7F_FFFF {
        return phase;
    }
    if (1.0..2.0).contains(&phase) {
        return phase - 1.0;
    }
    if !phase.is_finite() {
        return 0.0;
    }
    let w = phase - libm::floorf(phase);
    if (0.0..1.0).contains(&w) {
        w
    } else {
        0.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `wrap` as `phase − ⌊phase⌋` alone, as it was written before its fast cases.
    fn wrap_by_floor(phase: f32) -> f32 {
        if !phase.is_finite() {
            return 0.0;
        }
        let w = phase - libm::floorf(phase);
        if (0.0..1.0).contains(&w) {
            w
        } else {
            0.0
        }
    }

    /// `wrap`'s fast cases give `phase − ⌊phase⌋`'s bits: every f32 in \[0, 2\] at a stride, the
    /// edges (±0, the smallest subnormals, one ulp either side of 1 and 2), negative and large
    /// phases, ±∞ and NaN.
    #[test]
    fn wrap_is_phase_minus_its_floor_bit_for_bit() {
        let mut phases = vec![
            0.0f32,
            -0.0,
            1.0,
            2.0,
            1.0f32.next_down(),
            1.0f32.next_up(),
            2.0f32.next_down(),
            2.0f32.next_up(),
            f32::MIN_POSITIVE,
            -f32::MIN_POSITIVE,
            f32::from_bits(1),
            -f32::from_bits(1),
            -0.25,
            -1.0,
            3.75,
            1e9,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
        ];
        let mut bits = 0u32;
        while bits <= 2.0f32.to_bits() {
            phases.push(f32::from_bits(bits));
            bits += 997;
        }
        for phase in phases {
            assert_eq!(
                wrap(phase).to_bits(),
                wrap_by_floor(phase).to_bits(),
                "phase {phase:e}"
            );
        }
    }

    const T: f32 = 1e-4;

    /// The f32 sine in cycles against f64's over every 97th f32 in [0, 1) and the quadrant
    /// boundaries: within 1.2e-7 (1.02e-7 measured); libm's `sinf(2π·φ)` (what the generator
    /// used before) differs from it by at most 4.2e-7, mostly the rounding of the f32 product 2π·φ.
    #[test]
    fn sine_in_cycles_is_within_its_stated_error() {
        let (mut worst, mut from_old) = (0.0f64, 0.0f32);
        let mut check = |phase: f32| {
            let exact = (std::f64::consts::TAU * f64::from(phase)).sin();
            let e = (f64::from(sin_turns(phase)) - exact).abs();
            worst = worst.max(e);
            let old = libm::sinf(2.0 * core::f32::consts::PI * phase);
            from_old = from_old.max((sin_turns(phase) - old).abs());
        };
        let mut bits = 0u32;
        while bits < 1.0f32.to_bits() {
            check(f32::from_bits(bits));
            bits += 97;
        }
        for k in 0..=8 {
            let b = (k as f32 * 0.125).to_bits();
            for d in 0..64 {
                for p in [f32::from_bits(b.saturating_sub(d)), f32::from_bits(b + d)] {
                    if (0.0..1.0).contains(&p) {
                        check(p);
                    }
                }
            }
        }
        println!(
            "sin_turns: max error {worst:e}, max difference to libm's sinf(2π·φ) {from_old:e}"
        );
        assert!(worst <= 1.2e-7, "{worst:e}");
        assert!(from_old <= 5e-7, "{from_old:e}");
        assert!(sin_turns(f32::NAN).is_nan() && sin_turns(f32::INFINITY).is_nan());
        assert_eq!(sin_turns(0.0), 0.0);
        assert_eq!(sin_turns(0.25), 1.0);
        assert_eq!(sin_turns(0.75), -1.0);
    }

    /// The per-tick phase advance set with the program gives the stream the tick forms from
    /// `wrap(φ + f·T)` and `Wave::at`, bit for bit: per-axis programs (sine, triangle,
    /// steps, constant) switched with `set_program` to other frequencies, and a raster.
    #[test]
    fn phase_increments_give_the_recomputed_stream_bit_for_bit() {
        let wave = |kind: u8, f: f32| match kind {
            0 => Wave::Sine {
                offset: 19e-6,
                amplitude: 12e-6,
                frequency_hz: f,
            },
            1 => Wave::Triangle {
                offset: 3e-6,
                amplitude: 7e-6,
                frequency_hz: f,
            },
            2 => Wave::Steps {
                offset: 1e-6,
                amplitude: 2e-6,
                frequency_hz: f,
            },
            _ => Wave::Constant { offset: 5e-6 },
        };
        let period = 1.0 / 50_000.0f32;
        let mut g = ReferenceGenerator::new(Program::Streamed, period, [0.0; 2]);
        for (k, (fx, fy)) in [
            (10.0f32, 3.7f32),
            (1234.5, 0.3),
            (97.0, 24_999.0),
            (0.0, 7.0),
        ]
        .into_iter()
        .enumerate()
        {
            let waves = [wave(k as u8 % 4, fx), wave((k as u8 + 1) % 4, fy)];
            g.set_program(Program::PerAxis(waves));
            let mut phase = [0.0f32; 2];
            for tick in 0..20_000 {
                let want = [waves[0].at(phase[0]), waves[1].at(phase[1])];
                let got = g.next_setpoint();
                assert_eq!(got.map(f32::to_bits), want.map(f32::to_bits), "{k} {tick}");
                for (p, w) in phase.iter_mut().zip(waves) {
                    *p = wrap(*p + w.frequency_hz() * period);
                }
            }
        }
        let raster = Program::Raster {
            x_min: 0.0,
            x_max: 10e-6,
            y_min: 0.0,
            y_max: 4e-6,
            lines: 5,
            line_rate_hz: 333.0,
        };
        g.set_program(raster);
        let mut phase = 0.0f32;
        for tick in 0..20_000 {
            let x = 5e-6 + 5e-6 * triangle(phase);
            assert_eq!(g.next_setpoint()[0].to_bits(), x.to_bits(), "raster {tick}");
            phase = wrap(phase + 0.5 * 333.0 * period);
        }
    }

    #[test]
    fn sine_and_triangle_hit_their_extremes() {
        let mut g = ReferenceGenerator::new(
            Program::PerAxis([
                Wave::Sine {
                    offset: 10.0,
                    amplitude: 2.0,
                    frequency_hz: 100.0,
                },
                Wave::Triangle {
                    offset: 0.0,
                    amplitude: 1.0,
                    frequency_hz: 100.0,
                },
            ]),
            T,
            [0.0; 2],
        );
        let samples: std::vec::Vec<[f32; 2]> = (0..100).map(|_| g.next_setpoint()).collect();
        assert!((samples[0][0] - 10.0).abs() < 1e-6);
        assert!((samples[25][0] - 12.0).abs() < 1e-4);
        assert!((samples[75][0] - 8.0).abs() < 1e-4);
        assert!((samples[0][1] + 1.0).abs() < 1e-6);
        assert!((samples[50][1] - 1.0).abs() < 1e-4);
        // One full period later the waveform repeats.
        assert!((g.next_setpoint()[0] - 10.0).abs() < 1e-3);
    }

    #[test]
    fn steps_switch_at_half_period() {
        let w = Wave::Steps {
            offset: 1.0,
            amplitude: 0.5,
            frequency_hz: 10.0,
        };
        assert_eq!(w.at(0.1), 0.5);
        assert_eq!(w.at(0.6), 1.5);
    }

    #[test]
    fn raster_visits_every_row_and_returns() {
        let mut g = ReferenceGenerator::new(
            Program::Raster {
                x_min: 0.0,
                x_max: 1.0,
                y_min: 0.0,
                y_max: 3.0,
                lines: 4,
                line_rate_hz: 100.0,
            },
            T,
            [0.0; 2],
        );
        // 100 ticks per line; rows 0,1,2,3,2,1,0,...
        let mut rows = std::vec::Vec::new();
        for k in 0..800 {
            let [x, y] = g.next_setpoint();
            assert!((-1e-6..=1.0 + 1e-6).contains(&x));
            if k % 100 == 50 {
                rows.push(y.round() as i32);
            }
        }
        assert_eq!(rows, [0, 1, 2, 3, 2, 1, 0, 1]);
    }

    #[test]
    fn stream_plays_in_order_holds_and_counts_underruns() {
        let mut g = ReferenceGenerator::new(Program::Streamed, T, [5.0, 6.0]);
        assert_eq!(g.next_setpoint(), [5.0, 6.0]);
        assert_eq!(g.underruns(), 1);
        g.push_setpoint([1.0, 2.0]).unwrap();
        g.push_setpoint([3.0, 4.0]).unwrap();
        assert_eq!(g.queued(), 2);
        assert_eq!(g.next_setpoint(), [1.0, 2.0]);
        assert_eq!(g.next_setpoint(), [3.0, 4.0]);
        assert_eq!(g.next_setpoint(), [3.0, 4.0]);
        assert_eq!(g.underruns(), 2);
        for i in 0..STREAM_CAPACITY - 1 {
            g.push_setpoint([i as f32; 2]).unwrap();
        }
        assert_eq!(g.push_setpoint([9.0; 2]), Err([9.0; 2]));
    }

    #[test]
    fn table_interpolates_then_holds_or_repeats() {
        let mut g = ReferenceGenerator::new(
            Program::Table {
                ticks_per_entry: 2,
                repeat: false,
            },
            T,
            [7.0; 2],
        );
        assert_eq!(
            g.next_setpoint(),
            [7.0; 2],
            "empty table: the initial setpoint"
        );
        g.table_append(&[[0.0, 10.0], [2.0, 20.0], [4.0, 30.0]])
            .unwrap();
        g.set_program(g.program());
        let held: std::vec::Vec<f32> = (0..8).map(|_| g.next_setpoint()[0]).collect();
        assert_eq!(held, [0.0, 1.0, 2.0, 3.0, 4.0, 4.0, 4.0, 4.0]);
        g.set_program(Program::Table {
            ticks_per_entry: 2,
            repeat: true,
        });
        let repeated: std::vec::Vec<f32> = (0..8).map(|_| g.next_setpoint()[1]).collect();
        assert_eq!(repeated, [10.0, 15.0, 20.0, 25.0, 30.0, 20.0, 10.0, 15.0]);
        g.table_clear();
        assert!(g.table_append(&[[0.0; 2]; TABLE_CAPACITY]).is_ok());
        assert!(g.table_append(&[[0.0; 2]]).is_err());
        assert_eq!(g.table_len(), TABLE_CAPACITY);
    }

    /// The learned table at the wave table's position: the same entry, the same interpolation,
    /// the wrap to the first entry of a repeating table; the passes are counted at the entry
    /// played, and start again with the program.
    #[test]
    fn the_learned_table_plays_at_the_wave_tables_position() {
        let mut g = ReferenceGenerator::new(
            Program::Table {
                ticks_per_entry: 2,
                repeat: true,
            },
            T,
            [0.0; 2],
        );
        g.table_append(&[[0.0, 10.0], [2.0, 20.0], [4.0, 30.0]])
            .unwrap();
        g.learned_append(&[[10.0, 1.0], [30.0, 2.0], [20.0, 3.0]])
            .unwrap();
        assert_eq!(g.learned_len(), 3);
        let mut played = std::vec::Vec::new();
        for _ in 0..14 {
            let (r, u) = g.next_learned();
            played.push((r[0], u[0], u[1], g.pass()));
        }
        let expected = [
            (0.0, 10.0, 1.0, 0),
            (1.0, 20.0, 1.5, 0),
            (2.0, 30.0, 2.0, 0),
            (3.0, 25.0, 2.5, 0),
            (4.0, 20.0, 3.0, 0),
            (2.0, 15.0, 2.0, 0),
            (0.0, 10.0, 1.0, 1),
            (1.0, 20.0, 1.5, 1),
            (2.0, 30.0, 2.0, 1),
            (3.0, 25.0, 2.5, 1),
            (4.0, 20.0, 3.0, 1),
            (2.0, 15.0, 2.0, 1),
            (0.0, 10.0, 1.0, 2),
            (1.0, 20.0, 1.5, 2),
        ];
        assert_eq!(played, expected);
        // The plain setpoint path counts the passes the same way.
        g.set_program(g.program());
        assert_eq!(g.pass(), 0);
        let passes: std::vec::Vec<u32> = (0..13)
            .map(|_| {
                g.next_setpoint();
                g.pass()
            })
            .collect();
        assert_eq!(passes, [0, 0, 0, 0, 0, 0, 1, 1, 1, 1, 1, 1, 2]);
        // Held at the end without repeat: no pass completes.
        g.set_program(Program::Table {
            ticks_per_entry: 1,
            repeat: false,
        });
        for _ in 0..10 {
            g.next_learned();
        }
        assert_eq!((g.pass(), g.next_learned().1), (0, [20.0, 3.0]));
        // No learned table, or another program: NaN (the guard holds).
        g.learned_clear();
        assert!(g.next_learned().1.iter().all(|u| u.is_nan()));
        g.learned_append(&[[1.0; 2]; 3]).unwrap();
        g.set_program(Program::PerAxis([Wave::Constant { offset: 5.0 }; 2]));
        let (r, u) = g.next_learned();
        assert_eq!(r, [5.0; 2]);
        assert!(u.iter().all(|u| u.is_nan()));
        assert!(g.learned_append(&[[0.0; 2]; TABLE_CAPACITY - 2]).is_err());
        assert_eq!(g.learned_len(), 3);
    }

    /// The check's limits, at their edges: a step of exactly m·M passes and the next f32 up
    /// fails; the window's ends pass; the first failure in entry order is named.
    #[test]
    fn the_learned_check_holds_at_its_edges() {
        let limits = [
            LearnedLimits {
                window_v: [0.0, 120.0],
                max_step_v: 9.999998,
            },
            LearnedLimits {
                window_v: [-10.0, 100.0],
                max_step_v: 5.0,
            },
        ];
        let mut g = ReferenceGenerator::new(Program::Streamed, T, [0.0; 2]);
        assert_eq!(
            g.check_learned(1, true, &limits),
            Err(LearnedError::Length {
                learned: 0,
                wave: 0
            })
        );
        g.table_append(&[[0.0; 2]; 4]).unwrap();
        let check = |table: &[[f32; 2]], m: u32, repeat: bool| {
            let mut g = ReferenceGenerator::new(Program::Streamed, T, [0.0; 2]);
            g.table_append(&[[0.0; 2]; 4]).unwrap();
            g.learned_append(table).unwrap();
            g.check_learned(m, repeat, &limits)
        };
        let m = 9.999998f32;
        assert_eq!(
            check(
                &[[0.0, -10.0], [m, -5.0], [2.0 * m, 0.0], [m, -5.0]],
                1,
                true
            ),
            Ok(())
        );
        assert_eq!(
            check(
                &[[0.0, 0.0], [m.next_up(), 0.0], [0.0; 2], [0.0; 2]],
                1,
                false
            ),
            Err(LearnedError::Slew {
                entry: 1,
                axis: 0,
                step_v: m.next_up(),
                limit_v: m,
                ticks_per_entry: 1,
            })
        );
        // Three ticks per entry: 3·M.
        assert_eq!(
            check(
                &[[120.0, 100.0], [95.0, 85.0], [70.0, 70.0], [89.0, 85.0]],
                3,
                true
            ),
            Err(LearnedError::Slew {
                entry: 0,
                axis: 0,
                step_v: 31.0,
                limit_v: (3.0 * f64::from(m)) as f32,
                ticks_per_entry: 3,
            })
        );
        assert_eq!(
            check(
                &[[120.0, 100.0], [95.0, 85.0], [70.0, 70.0], [89.0, 85.0]],
                3,
                false
            ),
            Ok(())
        );
        assert_eq!(
            check(
                &[[0.0, 100.0], [0.0, 100.0f32.next_up()], [0.0; 2], [0.0; 2]],
                9,
                false
            ),
            Err(LearnedError::Window {
                entry: 1,
                axis: 1,
                value_v: 100.0f32.next_up(),
                window_v: [-10.0, 100.0],
            })
        );
        // Entry order first: the NaN of entry 2 before the window of entry 3.
        assert_eq!(
            check(
                &[[0.0; 2], [0.0; 2], [0.0, f32::NAN], [-1.0, 0.0]],
                1,
                false
            ),
            Err(LearnedError::NotFinite { entry: 2, axis: 1 })
        );
        assert_eq!(
            check(&[[0.0; 2]; 3], 1, false),
            Err(LearnedError::Length {
                learned: 3,
                wave: 4
            })
        );
    }

    #[test]
    fn phase_wrap_is_total() {
        for p in [f32::NAN, f32::INFINITY, -0.25, 1.0, 3.75, -1e-30] {
            let w = wrap(p);
            assert!((0.0..1.0).contains(&w), "{p} -> {w}");
        }
    }
}
