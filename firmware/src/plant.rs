//! A simulated piezo stage behind the converter traits, for the QEMU image and host tests.
//!
//! Not a model to identify against (that is `piezo-core`); just a plausible plant that a
//! feed-forward must fight, with independent, simple physics:
//!
//! ```text
//! u  = G_amp · V_dac                               actuator volts from the DAC code
//! p  = min(u + r, max(u − r, p₋))                  play (backlash) operator, half-width r volts
//! x  = x₋ + α · (k · p − x₋)                       first-order lag, α = 1 − exp(−T/τ), k m/V
//! V_sensor = x / (metres per volt)  →  AdcCode     sensor and ADC (default ±10.24 V range)
//! ```
//!
//! The plant advances one tick on each DAC write. DAC and ADC sides share one
//! `Cell<SimPlant>` (the plant is `Copy`), so [`PlantDac`] and [`PlantAdc`] can be borrowed
//! at the same time, as the loop needs, without `RefCell` panics.

use core::cell::Cell;
use core::convert::Infallible;

use crate::codes::{AdcCode, DacCode, SensorScale};
use crate::converter::{AdcRead, DacWrite, ErrorType};

/// Physical parameters of the simulated stage.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PlantParams {
    /// Piezo amplifier gain, actuator volts per DAC volt.
    pub amplifier_gain_v_per_v: f32,
    /// Static displacement per actuator volt, metres per volt.
    pub stroke_m_per_v: f32,
    /// Half-width of the play operator, actuator volts.
    pub play_half_width_v: f32,
    /// Lag coefficient per tick, `α = 1 − exp(−T/τ)`, in (0, 1].
    pub lag_alpha: f32,
    /// Displacement sensor gain.
    pub sensor: SensorScale,
}

/// State of the simulated stage.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SimPlant {
    params: PlantParams,
    play_output_v: f32,
    displacement_m: f32,
}

impl SimPlant {
    /// A stage at rest (0 V, 0 m).
    pub fn new(params: PlantParams) -> Self {
        Self {
            params,
            play_output_v: 0.0,
            displacement_m: 0.0,
        }
    }

    /// Current displacement in metres.
    pub fn displacement_m(&self) -> f32 {
        self.displacement_m
    }

    /// Advances one tick with the DAC at `code`.
    pub fn step(&mut self, code: DacCode) {
        let p = &self.params;
        let u = code.to_volts() * p.amplifier_gain_v_per_v;
        let r = p.play_half_width_v;
        self.play_output_v = self.play_output_v.max(u - r).min(u + r);
        let target = p.stroke_m_per_v * self.play_output_v;
        self.displacement_m += p.lag_alpha * (target - self.displacement_m);
    }

    /// What the ADC reads now.
    pub fn sensor_code(&self) -> AdcCode {
        AdcCode::from_volts(self.params.sensor.volts(self.displacement_m))
    }
}

/// DAC side of a shared [`SimPlant`]; one channel.
pub struct PlantDac<'a>(pub &'a Cell<SimPlant>);

/// ADC side of a shared [`SimPlant`]; one channel.
pub struct PlantAdc<'a>(pub &'a Cell<SimPlant>);

impl ErrorType for PlantDac<'_> {
    type Error = Infallible;
}

impl ErrorType for PlantAdc<'_> {
    type Error = Infallible;
}

impl DacWrite for PlantDac<'_> {
    type Channel = ();

    fn write_code(&mut self, _channel: (), code: DacCode) -> Result<(), Infallible> {
        let mut plant = self.0.get();
        plant.step(code);
        self.0.set(plant);
        Ok(())
    }
}

impl AdcRead for PlantAdc<'_> {
    type Channel = ();

    fn read_code(&mut self, _channel: ()) -> Result<AdcCode, Infallible> {
        Ok(self.0.get().sensor_code())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn params() -> PlantParams {
        PlantParams {
            amplifier_gain_v_per_v: 20.0,
            stroke_m_per_v: 0.15e-6,
            play_half_width_v: 2.0,
            lag_alpha: 0.5,
            sensor: SensorScale::new(1.5e-6).unwrap(),
        }
    }

    #[test]
    fn settles_to_static_gain_minus_play() {
        let mut plant = SimPlant::new(params());
        let code = DacCode::from_volts(2.5); // 50 V at the actuator
        for _ in 0..100 {
            plant.step(code);
        }
        // Rising from 0: the play output lags the input by r = 2 V, so x = k (u − r).
        let expected = 0.15e-6 * (code.to_volts() * 20.0 - 2.0);
        assert!((plant.displacement_m() - expected).abs() < 1e-12);
        let sensed = AdcCode::to_volts(plant.sensor_code()) * 1.5e-6;
        assert!((sensed - expected).abs() < AdcCode::VOLTS_PER_LSB * 1.5e-6);
    }

    #[test]
    fn play_gives_hysteresis_between_up_and_down_branches() {
        let mut plant = SimPlant::new(params());
        let mid = DacCode::from_volts(2.5);
        for _ in 0..100 {
            plant.step(mid);
        }
        let rising = plant.displacement_m();
        for _ in 0..100 {
            plant.step(DacCode::from_volts(5.0));
        }
        for _ in 0..100 {
            plant.step(mid);
        }
        let falling = plant.displacement_m();
        // Same input, branches 2 r k apart.
        assert!(((falling - rising) - 2.0 * 2.0 * 0.15e-6).abs() < 1e-11);
    }

    #[test]
    fn dac_and_adc_sides_share_the_plant() {
        let cell = Cell::new(SimPlant::new(params()));
        let (mut dac, mut adc) = (PlantDac(&cell), PlantAdc(&cell));
        assert_eq!(adc.read_code(()).unwrap(), AdcCode::MID_SCALE);
        dac.write_code((), DacCode::MAX).unwrap();
        assert!(adc.read_code(()).unwrap() > AdcCode::MID_SCALE);
    }
}
