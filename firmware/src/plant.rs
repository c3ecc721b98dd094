//! A simulated two-axis piezo stage behind the converter traits, for the QEMU image and host tests.
//!
//! Deliberately *not* the core's model: each axis is its own f32 Bouc-Wen operator integrated
//! with explicit Euler sub-steps in the input (not `piezo_core`'s exact path integral), followed by
//! a first-order lag, so that the compensator is checked against dynamics it does not contain
//! (the lag) and an integrator it does not share:
//!
//! ```text
//! u  = G_amp · V_dac                                         actuator volts (zero-order hold)
//! per tick, m = ⌈|u − u₋| / δu_max⌉ Euler sub-steps of δu = (u − u₋)/m:
//!     h += A·δu − β·|δu|·|h|^(n−1)·h − γ·δu·|h|^n            (Bouc-Wen, rate-independent form)
//! y  = k1·u + k2·h + y0                                       static map (same parameters as the
//!                                                             parameter file)
//! x  = x₋ + α·(y − x₋),  α = 1 − exp(−T/τ)                   first-order lag (stage mechanics)
//! c  = c₋ + α_c·(g_c·(u − u_rest) − c₋),  α_c = 1 − exp(−T/τ_c)   creep (optional)
//! d  = d₋ + ḋ·T                                               drift (optional)
//! V_sensor = (x + c + d) / (metres per volt) + noise  →  AdcCode   sensor and ADC (±10.24 V)
//! ```
//!
//! Creep, drift and sensor noise ([`Disturbances`], all zero by default) are what the servo
//! table of [`crate::servo_table`] needs: effects no feed-forward model of the image holds. The
//! noise is uniform with the given RMS, from a hash of the tick and the axis (no state, the
//! same on every run).
//!
//! Time is explicit: the DAC side sets an axis's input code (held), the ADC side reads the
//! current displacement, and [`XyPlant::advance`] moves the stage one loop period on. The two
//! sides share one `Cell<XyPlant>` (the plant is `Copy`), so [`PlantDac`] and [`PlantAdc`] can be
//! borrowed at the same time without `RefCell` panics.

use core::cell::Cell;
use core::convert::Infallible;

use piezo_core::{BoucWenParams, StaticMap};

use crate::codes::{AdcCode, DacCode, SensorScale};
use crate::converter::{AdcRead, DacWrite, ErrorType};
use crate::xy_loop::{AdcSensor, Axis, XyIo};

/// Largest input change per Euler sub-step \[V\].
pub const MAX_SUBSTEP_V: f32 = 0.05;
/// Most Euler sub-steps in one tick.
pub const MAX_SUBSTEPS: u32 = 512;
/// Lag time constant of the simulated stage mechanics \[s\] (first mode ≈ 3.2 kHz: 1/(2π·3.2 kHz)).
pub const LAG_TIME_CONSTANT_S: f32 = 50e-6;

/// What the simulated stage adds that no model of the image holds (all zero: nothing).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Disturbances {
    /// g_c: creep gain \[m/V\] (its settled share of the input above the rest voltage).
    pub creep_gain_m_per_v: f32,
    /// τ_c: creep time constant \[s\] (> 0 when the gain is not 0).
    pub creep_time_constant_s: f32,
    /// ḋ: drift of the output \[m/s\].
    pub drift_m_per_s: f32,
    /// RMS of the sensor noise \[m\].
    pub sensor_noise_rms_m: f32,
}

/// One axis of the simulated stage.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StackPlant {
    bouc_wen: BoucWenParams,
    map: StaticMap,
    lag_alpha: f32,
    input_v: f32,
    h: f32,
    displacement_m: f32,
    rest_v: f32,
    creep_alpha: f32,
    creep_gain_m_per_v: f32,
    creep_m: f32,
    drift_step_m: f32,
    drift_m: f32,
}

impl StackPlant {
    /// At rest at `input_v` (h = 0, settled), with lag `α = 1 − exp(−T/τ)`.
    pub fn new(bouc_wen: BoucWenParams, map: StaticMap, lag_alpha: f32, input_v: f32) -> Self {
        Self {
            bouc_wen,
            map,
            lag_alpha,
            input_v,
            h: 0.0,
            displacement_m: map.output(input_v, 0.0),
            rest_v: input_v,
            creep_alpha: 0.0,
            creep_gain_m_per_v: 0.0,
            creep_m: 0.0,
            drift_step_m: 0.0,
            drift_m: 0.0,
        }
    }

    /// This axis with creep and drift at loop period `sample_period_s` \[s\].
    pub fn with_disturbances(mut self, d: &Disturbances, sample_period_s: f32) -> Self {
        self.creep_gain_m_per_v = d.creep_gain_m_per_v;
        self.creep_alpha = if d.creep_time_constant_s > 0.0 {
            1.0 - libm::expf(-sample_period_s / d.creep_time_constant_s)
        } else {
            0.0
        };
        self.drift_step_m = d.drift_m_per_s * sample_period_s;
        self
    }

    /// Hysteretic state h.
    pub fn h(&self) -> f32 {
        self.h
    }

    /// Displacement \[m\]: the lagged hysteresis output plus creep and drift.
    pub fn displacement_m(&self) -> f32 {
        self.displacement_m + self.creep_m + self.drift_m
    }

    /// Moves the input to `input_v` along a straight path and advances the lag one period.
    pub fn advance(&mut self, input_v: f32) {
        let BoucWenParams { a, beta, gamma, n } = self.bouc_wen;
        let du = input_v - self.input_v;
        let substeps = libm::ceilf(du.abs() / MAX_SUBSTEP_V).clamp(1.0, MAX_SUBSTEPS as f32);
        let step = du / substeps;
        let mut h = self.h;
        let mut i = 0.0;
        while i < substeps {
            let magnitude = if n == 1.0 {
                h.abs()
            } else {
                libm::powf(h.abs(), n)
            };
            let sign = if h < 0.0 { -1.0 } else { 1.0 };
            h += a * step - beta * step.abs() * magnitude * sign - gamma * step * magnitude;
            i += 1.0;
        }
        self.h = h;
        self.input_v = input_v;
        let target = self.map.output(input_v, h);
        self.displacement_m += self.lag_alpha * (target - self.displacement_m);
        let creep_target = self.creep_gain_m_per_v * (input_v - self.rest_v);
        self.creep_m += self.creep_alpha * (creep_target - self.creep_m);
        self.drift_m += self.drift_step_m;
    }
}

/// The two-axis stage: two [`StackPlant`]s, the amplifier and the sensor.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct XyPlant {
    axes: [StackPlant; 2],
    codes: [DacCode; 2],
    amplifier_gain_v_per_v: f32,
    sensor: SensorScale,
    /// Half-width of the uniform sensor noise \[m\] (√3 × its RMS).
    noise_half_width_m: f32,
    ticks: u32,
}

impl XyPlant {
    /// A stage at rest with both DAC codes at 0.
    pub fn new(axes: [StackPlant; 2], amplifier_gain_v_per_v: f32, sensor: SensorScale) -> Self {
        Self {
            axes,
            codes: [DacCode::SAFE; 2],
            amplifier_gain_v_per_v,
            sensor,
            noise_half_width_m: 0.0,
            ticks: 0,
        }
    }

    /// This stage with creep, drift and sensor noise on both axes.
    pub fn with_disturbances(mut self, d: &Disturbances, sample_period_s: f32) -> Self {
        for axis in &mut self.axes {
            *axis = axis.with_disturbances(d, sample_period_s);
        }
        self.noise_half_width_m = libm::sqrtf(3.0) * d.sensor_noise_rms_m;
        self
    }

    /// The stage of the built-in parameter file ([`crate::params`]), lag
    /// [`LAG_TIME_CONSTANT_S`], at rest at the lower end of each window.
    pub fn from_params(sample_period_s: f32) -> Option<Self> {
        use crate::params::{AMPLIFIER_GAIN_V_PER_V, AXES, SENSOR_M_PER_V};
        let alpha = 1.0 - libm::expf(-sample_period_s / LAG_TIME_CONSTANT_S);
        let axis = |i: usize| {
            let p = AXES[i];
            StackPlant::new(p.bouc_wen, p.static_map, alpha, p.limits.output_min_v)
        };
        Some(Self::new(
            [axis(0), axis(1)],
            AMPLIFIER_GAIN_V_PER_V,
            SensorScale::new(SENSOR_M_PER_V)?,
        ))
    }

    /// One axis.
    pub fn axis(&self, axis: Axis) -> &StackPlant {
        &self.axes[axis.index()]
    }

    /// Sets an axis's DAC code (takes effect at the next [`XyPlant::advance`]).
    pub fn set_code(&mut self, axis: Axis, code: DacCode) {
        self.codes[axis.index()] = code;
    }

    /// The DAC code an axis holds.
    pub fn code(&self, axis: Axis) -> DacCode {
        self.codes[axis.index()]
    }

    /// One loop period on, with the held DAC codes.
    pub fn advance(&mut self) {
        for (plant, code) in self.axes.iter_mut().zip(self.codes) {
            plant.advance(code.to_volts() * self.amplifier_gain_v_per_v);
        }
        self.ticks = self.ticks.wrapping_add(1);
    }

    /// What the ADC reads for an axis now.
    pub fn sensor_code(&self, axis: Axis) -> AdcCode {
        let noise = if self.noise_half_width_m > 0.0 {
            self.noise_half_width_m * uniform(self.ticks, axis.index() as u32)
        } else {
            0.0
        };
        AdcCode::from_volts(self.sensor.volts(self.axis(axis).displacement_m() + noise))
    }
}

/// A number in \[−1, 1) from a hash of `tick` and `axis` (a 32-bit integer mix).
fn uniform(tick: u32, axis: u32) -> f32 {
    let mut z = tick.wrapping_mul(0x9E37_79B9) ^ axis.wrapping_mul(0x85EB_CA6B);
    z = (z ^ (z >> 16)).wrapping_mul(0x7FEB_352D);
    z = (z ^ (z >> 15)).wrapping_mul(0x846C_A68B);
    z ^= z >> 16;
    (z >> 8) as f32 / (1u32 << 23) as f32 - 1.0
}

/// The loop's I/O on a shared [`XyPlant`]: its DAC and its ADC read through `scale`, channel =
/// axis for both.
pub fn plant_io(
    plant: &Cell<XyPlant>,
    scale: SensorScale,
) -> XyIo<PlantDac<'_>, AdcSensor<PlantAdc<'_>>> {
    XyIo {
        dac: PlantDac(plant),
        dac_channels: Axis::ALL,
        sensor: AdcSensor {
            adc: PlantAdc(plant),
            channels: Axis::ALL,
            scale,
        },
    }
}

/// DAC side of a shared [`XyPlant`]; channel = axis.
pub struct PlantDac<'a>(pub &'a Cell<XyPlant>);

/// ADC side of a shared [`XyPlant`]; channel = axis.
pub struct PlantAdc<'a>(pub &'a Cell<XyPlant>);

impl ErrorType for PlantDac<'_> {
    type Error = Infallible;
}

impl ErrorType for PlantAdc<'_> {
    type Error = Infallible;
}

impl DacWrite for PlantDac<'_> {
    type Channel = Axis;

    fn write_code(&mut self, channel: Axis, code: DacCode) -> Result<(), Infallible> {
        let mut plant = self.0.get();
        plant.set_code(channel, code);
        self.0.set(plant);
        Ok(())
    }
}

impl AdcRead for PlantAdc<'_> {
    type Channel = Axis;

    fn read_code(&mut self, channel: Axis) -> Result<AdcCode, Infallible> {
        Ok(self.0.get().sensor_code(channel))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::params::AXES;
    use piezo_core::{BoucWen, HysteresisState};

    fn stack(i: usize) -> StackPlant {
        StackPlant::new(AXES[i].bouc_wen, AXES[i].static_map, 1.0, 0.0)
    }

    /// The Euler plant and the core's exact step agree on the first loading (to the Euler
    /// error), yet are different integrators.
    #[test]
    fn euler_plant_follows_the_bouc_wen_law() {
        for (i, axis) in AXES.iter().enumerate() {
            let mut plant = stack(i);
            let bw = BoucWen::new(axis.bouc_wen).unwrap();
            let mut state = HysteresisState::at_rest(0.0);
            for k in 1..=1200 {
                let u = k as f32 * 0.1;
                plant.advance(u);
                bw.step(&mut state, u);
            }
            assert!(
                (plant.h() - state.h).abs() < 2e-3 * state.h.abs(),
                "{} vs {}",
                plant.h(),
                state.h
            );
            // First loading to 120 V gives the 38 µm free stroke the file was built for.
            assert!(
                (plant.displacement_m() - 38e-6).abs() < 0.1e-6,
                "{}",
                plant.displacement_m()
            );
        }
    }

    #[test]
    fn branches_differ_at_the_same_input() {
        let mut plant = stack(0);
        plant.advance(60.0);
        let rising = plant.displacement_m();
        plant.advance(120.0);
        plant.advance(60.0);
        let falling = plant.displacement_m();
        assert!(falling - rising > 1e-6, "{rising} {falling}");
    }

    #[test]
    fn dac_and_adc_sides_share_the_plant_and_time_is_explicit() {
        let cell = Cell::new(XyPlant::from_params(1e-4).unwrap());
        let (mut dac, mut adc) = (PlantDac(&cell), PlantAdc(&cell));
        assert_eq!(adc.read_code(Axis::X).unwrap(), AdcCode::MID_SCALE);
        dac.write_code(Axis::X, DacCode(30_000)).unwrap();
        assert_eq!(adc.read_code(Axis::X).unwrap(), AdcCode::MID_SCALE);
        let mut p = cell.get();
        p.advance();
        cell.set(p);
        assert!(adc.read_code(Axis::X).unwrap() > AdcCode::MID_SCALE);
        assert_eq!(adc.read_code(Axis::Y).unwrap(), AdcCode::MID_SCALE);
    }
}
