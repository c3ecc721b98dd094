//! The control tick's deadline, measured: the DWT cycle counter (CYCCNT, one count per core
//! clock cycle, 168 MHz) stamps each tick's start and end, and TIM2's counter (`CNT`, counting
//! up from 0 at each update, 84 MHz) says how long ago the update that started the tick came.
//!
//! With `T` the loop period in core cycles, `e` a tick's entry stamp, `c` the timer count read at
//! entry and `k = f_core / f_timer` (2 here):
//!
//! ```text
//! update     u = e − k·c                 the update the tick serves (the latest one before e)
//! cost         = end − e                 the tick's own cycles (sensor → … → DAC, frame encoding)
//! latency      = e − u                   update to entry (a lower-priority lock or a defmt record)
//! completion   = end − u                 what the deadline bounds: late if completion > T, or if
//!                                        TIM2's update flag is set again when the tick ends
//! skipped      = round((u − u_prev)/T) − 1   updates that got no tick of their own
//! ```
//!
//! A late tick or a skipped update is a missed deadline: the next tick (or, for a skipped update,
//! this one) tells the loop so (`deadline_missed`), which counts an overrun and latches the safe
//! state ([`crate::xy_loop`]'s Deadline). The worst cost, latency and completion since boot are
//! kept in [`TickStats`] and logged once a second by the board image.
//!
//! CYCCNT wraps every 2³² cycles (25.6 s at 168 MHz); every difference here is a wrapping one
//! between two stamps less than a few periods apart.

/// What the board has measured of its ticks since boot (core cycles; 168 per µs).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct TickStats {
    /// Ticks measured.
    pub ticks: u32,
    /// The last tick's cost (entry to end) \[cycles\].
    pub last_cycles: u32,
    /// The largest cost \[cycles\].
    pub worst_cycles: u32,
    /// The largest update-to-entry latency \[cycles\].
    pub worst_latency_cycles: u32,
    /// The largest update-to-end time \[cycles\]; the deadline is one period.
    pub worst_completion_cycles: u32,
    /// Ticks that ended after the next update (deadline missed).
    pub late_ticks: u32,
    /// Timer updates that got no tick (the tick before was held off for more than a period).
    pub skipped_updates: u32,
}

/// The stamps of a tick in progress, from [`DeadlineMonitor::start`].
#[derive(Clone, Copy, Debug)]
pub struct TickStart {
    entry_cycles: u32,
    update_cycles: u32,
}

/// Measures each tick against the loop period.
#[derive(Clone, Debug)]
pub struct DeadlineMonitor {
    period_cycles: u32,
    cycles_per_timer_tick: u32,
    previous_update: Option<u32>,
    stats: TickStats,
}

impl DeadlineMonitor {
    /// A monitor for a loop period of `period_cycles` core cycles, with a timer that counts once
    /// every `cycles_per_timer_tick` core cycles.
    pub fn new(period_cycles: u32, cycles_per_timer_tick: u32) -> Self {
        Self {
            period_cycles: period_cycles.max(1),
            cycles_per_timer_tick,
            previous_update: None,
            stats: TickStats::default(),
        }
    }

    /// The loop period \[core cycles\].
    pub fn period_cycles(&self) -> u32 {
        self.period_cycles
    }

    /// At a tick's entry: `entry_cycles` is CYCCNT, `timer_count` the timer's counter (ticks
    /// since its latest update). Returns the stamps for [`Self::finish`] and true if updates
    /// since the previous tick's went without a tick (a missed deadline).
    pub fn start(&mut self, entry_cycles: u32, timer_count: u32) -> (TickStart, bool) {
        let since_update = timer_count.wrapping_mul(self.cycles_per_timer_tick);
        let update_cycles = entry_cycles.wrapping_sub(since_update);
        let s = &mut self.stats;
        s.worst_latency_cycles = s.worst_latency_cycles.max(since_update);
        let period = u64::from(self.period_cycles);
        let skipped = self.previous_update.map_or(0, |previous| {
            // Stamps are less than half the counter's range apart: a larger difference is an
            // estimate a few cycles before `previous` (the same update), no period passed.
            let elapsed = update_cycles.wrapping_sub(previous);
            let elapsed = if elapsed > 1 << 31 {
                0
            } else {
                u64::from(elapsed)
            };
            let periods = (elapsed + period / 2) / period;
            u32::try_from(periods).map_or(u32::MAX, |p| p.saturating_sub(1))
        });
        s.skipped_updates = s.skipped_updates.saturating_add(skipped);
        self.previous_update = Some(update_cycles);
        let start = TickStart {
            entry_cycles,
            update_cycles,
        };
        (start, skipped > 0)
    }

    /// At a tick's end: `end_cycles` is CYCCNT, `next_update_seen` whether the timer's update
    /// flag (cleared at entry) is set again. Returns true if the tick missed its deadline.
    pub fn finish(&mut self, start: TickStart, end_cycles: u32, next_update_seen: bool) -> bool {
        let cost = end_cycles.wrapping_sub(start.entry_cycles);
        let completion = end_cycles.wrapping_sub(start.update_cycles);
        let late = next_update_seen || completion > self.period_cycles;
        let s = &mut self.stats;
        s.ticks = s.ticks.wrapping_add(1);
        s.last_cycles = cost;
        s.worst_cycles = s.worst_cycles.max(cost);
        s.worst_completion_cycles = s.worst_completion_cycles.max(completion);
        if late {
            s.late_ticks = s.late_ticks.saturating_add(1);
        }
        late
    }

    /// What has been measured so far.
    pub fn stats(&self) -> TickStats {
        self.stats
    }
}
