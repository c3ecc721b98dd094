//! Raw converter codes as newtypes, and their conversion to and from SI units.
//!
//! - [`DacCode`]: TI DAC8563 input code, straight binary, 16 bit. With the internal 2.5 V
//!   reference enabled the output gain is 2 (DAC8563 datasheet, sections "Internal Reference"
//!   and "Gain Register"), so `V_OUT = code · 5 V / 2^16` (section "DAC Transfer Function").
//! - [`AdcCode`]: TI ADS8681 conversion result, straight binary, 16 bit, for both bipolar and
//!   unipolar ranges (ADS8681 datasheet, section "ADC Transfer Function": bipolar ranges put
//!   0 V at code 0x8000). The constants here are for the range the driver configures by
//!   default, ±2.5 · V_REF = ±10.24 V with the internal 4.096 V reference; other ranges use
//!   [`InputRange`](crate::ads8681::InputRange) from the driver.
//! - [`SensorScale`]: displacement sensor gain, metres per volt of sensor output.
//!
//! Every conversion from `f32` saturates to the code range, rounds to nearest, never panics, and
//! maps NaN to a documented safe code.

/// DAC8563 input code (16-bit straight binary): `V_OUT = code · DacCode::VOLTS_PER_LSB`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, Default)]
pub struct DacCode(pub u16);

impl DacCode {
    /// Full-scale output span: internal reference 2.5 V times gain 2.
    pub const FULL_SCALE_VOLTS: f32 = 5.0;
    /// Output volts per code step: 5 V / 2^16 ≈ 76.3 µV.
    pub const VOLTS_PER_LSB: f32 = Self::FULL_SCALE_VOLTS / 65_536.0;
    /// Code 0 = 0 V: the piezo amplifier input at rest. Used for NaN requests.
    pub const SAFE: DacCode = DacCode(0);
    /// Largest code, `5 V − 1 LSB`.
    pub const MAX: DacCode = DacCode(u16::MAX);

    /// Nearest code to `volts` at the DAC output, saturated to `[0, 65535]`; NaN gives
    /// [`DacCode::SAFE`]. Never panics.
    ///
    /// `code = sat₀⁶⁵⁵³⁵(⌊volts / LSB + 0.5⌋)`: Rust's float → `u32` cast truncates towards zero
    /// and saturates (below 0 → 0, NaN → 0 = [`DacCode::SAFE`]; the Cortex-M4F's `vcvt` does
    /// exactly that, one instruction), then the integer minimum with 65 535 (above it, or +∞ →
    /// 65 535): the same codes as the float → `u16` cast, without its two float compares. The
    /// same codes as clamping `volts / LSB` to \[0, 65 535\] first: inside that range the sum is
    /// the same; below it the sum is < 0.5 and truncates to 0; above it the sum is > 65 535.5.
    #[inline]
    pub fn from_volts(volts: f32) -> Self {
        let code = (volts / Self::VOLTS_PER_LSB + 0.5) as u32;
        // At most u16::MAX after the minimum: the cast keeps the value.
        DacCode(code.min(u32::from(u16::MAX)) as u16)
    }

    /// DAC output volts for this code.
    #[inline]
    pub fn to_volts(self) -> f32 {
        self.0 as f32 * Self::VOLTS_PER_LSB
    }
}

/// ADS8681 conversion result (16-bit straight binary, range ±10.24 V by default).
///
/// `V_IN = (code − 0x8000) · AdcCode::VOLTS_PER_LSB` for the bipolar default range.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, Default)]
pub struct AdcCode(pub u16);

impl AdcCode {
    /// Code of 0 V input for bipolar ranges.
    pub const MID_SCALE: AdcCode = AdcCode(0x8000);
    /// Input span of the default range: 2 · 2.5 · 4.096 V = 20.48 V.
    pub const SPAN_VOLTS: f32 = 20.48;
    /// Input volts per code step: 20.48 V / 2^16 = 312.5 µV.
    pub const VOLTS_PER_LSB: f32 = Self::SPAN_VOLTS / 65_536.0;

    /// Input volts for this code in the default ±10.24 V range.
    #[inline]
    pub fn to_volts(self) -> f32 {
        (self.0 as i32 - 0x8000) as f32 * Self::VOLTS_PER_LSB
    }

    /// Nearest code for `volts` at the input, saturated to the range; NaN gives
    /// [`AdcCode::MID_SCALE`] (0 V). Used by simulated plants and tests. Never panics.
    #[inline]
    pub fn from_volts(volts: f32) -> Self {
        if volts.is_nan() {
            return Self::MID_SCALE;
        }
        let lsb = (volts / Self::VOLTS_PER_LSB + 32_768.0).clamp(0.0, u16::MAX as f32);
        AdcCode((lsb + 0.5) as u16)
    }
}

/// Displacement sensor gain: metres of displacement per volt of sensor output.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SensorScale {
    metres_per_volt: f32,
}

impl SensorScale {
    /// A sensor scale; `None` unless `metres_per_volt` is finite and non-zero.
    pub fn new(metres_per_volt: f32) -> Option<Self> {
        (metres_per_volt.is_finite() && metres_per_volt != 0.0).then_some(Self { metres_per_volt })
    }

    /// Metres per volt.
    pub fn metres_per_volt(&self) -> f32 {
        self.metres_per_volt
    }

    /// Displacement for a sensor voltage.
    #[inline]
    pub fn metres(&self, volts: f32) -> f32 {
        volts * self.metres_per_volt
    }

    /// Sensor voltage for a displacement.
    #[inline]
    pub fn volts(&self, metres: f32) -> f32 {
        metres / self.metres_per_volt
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn dac_code_endpoints_and_saturation() {
        assert_eq!(DacCode::from_volts(0.0), DacCode(0));
        assert_eq!(DacCode::from_volts(-1.0), DacCode(0));
        assert_eq!(DacCode::from_volts(2.5), DacCode(32_768));
        assert_eq!(DacCode::from_volts(5.0), DacCode::MAX);
        assert_eq!(DacCode::from_volts(1e30), DacCode::MAX);
        assert_eq!(DacCode::from_volts(f32::INFINITY), DacCode::MAX);
        assert_eq!(DacCode::from_volts(f32::NEG_INFINITY), DacCode(0));
        assert_eq!(DacCode::from_volts(f32::NAN), DacCode::SAFE);
        assert_eq!(DacCode::from_volts(-f32::NAN), DacCode::SAFE);
    }

    /// The clamped form the conversion is equal to, bit for bit.
    fn dac_code_clamped(volts: f32) -> DacCode {
        if volts.is_nan() {
            return DacCode::SAFE;
        }
        let lsb = (volts / DacCode::VOLTS_PER_LSB).clamp(0.0, u16::MAX as f32);
        DacCode((lsb + 0.5) as u16)
    }

    /// Every f32 bit pattern (all 2³² values, NaNs, ±∞, subnormals, ±0) gives the clamped
    /// form's code.
    #[test]
    fn dac_code_equals_the_clamped_conversion_for_every_f32() {
        let mut bits = 0u32;
        loop {
            let v = f32::from_bits(bits);
            assert_eq!(
                DacCode::from_volts(v),
                dac_code_clamped(v),
                "{v} ({bits:#x})"
            );
            match bits.checked_add(1) {
                Some(b) => bits = b,
                None => break,
            }
        }
    }

    #[test]
    fn dac_code_round_trip_is_exact() {
        for code in 0..=u16::MAX {
            assert_eq!(DacCode::from_volts(DacCode(code).to_volts()), DacCode(code));
        }
    }

    #[test]
    fn adc_code_round_trip_is_exact_and_mid_scale_is_zero() {
        assert_eq!(AdcCode::MID_SCALE.to_volts(), 0.0);
        assert_eq!(AdcCode(0).to_volts(), -10.24);
        for code in 0..=u16::MAX {
            assert_eq!(AdcCode::from_volts(AdcCode(code).to_volts()), AdcCode(code));
        }
        assert_eq!(AdcCode::from_volts(f32::NAN), AdcCode::MID_SCALE);
        assert_eq!(AdcCode::from_volts(f32::INFINITY), AdcCode(u16::MAX));
        assert_eq!(AdcCode::from_volts(f32::NEG_INFINITY), AdcCode(0));
    }

    /// Every 97th f32 bit pattern (44 million values, all classes) converts without panicking
    /// and lands on a monotone, in-range code.
    #[test]
    fn dac_code_conversion_total_over_f32_sweep() {
        let mut bits = 0u32;
        loop {
            let v = f32::from_bits(bits);
            let code = DacCode::from_volts(v);
            if v.is_nan() || v <= 0.0 {
                assert_eq!(code, DacCode(0), "{v}");
            } else if v >= DacCode::FULL_SCALE_VOLTS {
                assert_eq!(code, DacCode::MAX, "{v}");
            }
            let _ = AdcCode::from_volts(v);
            match bits.checked_add(97) {
                Some(b) => bits = b,
                None => break,
            }
        }
    }

    proptest! {
        #[test]
        fn dac_code_error_at_most_half_lsb(v in 0.0f32..DacCode::FULL_SCALE_VOLTS - DacCode::VOLTS_PER_LSB) {
            let err = (DacCode::from_volts(v).to_volts() - v).abs();
            prop_assert!(err <= 0.5 * DacCode::VOLTS_PER_LSB * 1.001, "v={v} err={err}");
        }

        #[test]
        fn sensor_scale_round_trip(m in -20e-6f32..20e-6, k in 1e-7f32..1e-5) {
            let s = SensorScale::new(k).unwrap();
            let back = s.metres(s.volts(m));
            prop_assert!((back - m).abs() <= 1e-6 * m.abs() + 1e-12);
        }
    }

    #[test]
    fn sensor_scale_rejects_degenerate_gains() {
        assert!(SensorScale::new(0.0).is_none());
        assert!(SensorScale::new(f32::NAN).is_none());
        assert!(SensorScale::new(f32::INFINITY).is_none());
        assert!(SensorScale::new(1.5e-6).is_some());
    }
}
