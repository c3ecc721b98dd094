//! The stage file as the firmware runs it: [`FirmwareSet::from_bytes`] is the one way from a
//! stage file's bytes to the parameter set an image is built with (`firmware/build/params.rs`)
//! and an upload carries (`host-sim link upload`).
//!
//! It reads the file ([`StageFile::parse`]), refuses a model family the firmware's chain does not
//! run (it runs the static models, `symmetric` and `asymmetric`: [`ModelKind::runs_on_firmware`]),
//! validates the rest as [`StageFile::validate`] does (the core's constructors with their
//! plausibility bounds, `IoChain::check_limits`), and gives per axis the core's parameter structs
//! with the window, the slew limit and the first loading from rest at the lower end of the window
//! (rest output y_rest and secant gain g_lin = (y(u_max) − y_rest)/(u_max − u_min), the
//! uncompensated baseline u = u_min + (r − y_rest)/g_lin). A one-axis file drives both channels
//! with its `x` set. The set carries the version string `name version` and the FNV-1a hash of
//! the file's bytes ([`fnv1a32`]), which the firmware prints at boot and reports in its status.
//!
//! Every refusal names the file, line, column and key ([`StageError`]). What one image's
//! hardware needs on top (its DAC and ADC parts, its loop-rate range) is the image's build's.

use crate::{fnv1a32, AxisChain, StageError, StageErrorKind, StageFile, ValidAxis};
use piezo_core::{Asymmetry, AxisParams, BoucWenParams, IoChain, StaticMap};

/// A stage file as the firmware runs it (see the module doc).
#[derive(Debug, Clone, PartialEq)]
pub struct FirmwareSet {
    /// The file as read (its `[io]` table, for what an image checks on top).
    pub file: StageFile,
    /// `name` and `version` of the stage, joined by a space.
    pub version: String,
    /// FNV-1a (32 bit) of the file's bytes.
    pub fnv1a32: u32,
    /// Loop rate \[Hz\].
    pub loop_rate_hz: f32,
    /// The whole chain (DAC, amplifier, ADC, sensor), as an upload must carry it.
    pub io: IoChain,
    /// x then y (x twice for a one-axis file).
    pub axes: [AxisParams; 2],
}

impl FirmwareSet {
    /// The set of the stage file `file` (its name, for messages) with contents `bytes`.
    pub fn from_bytes(file: &str, bytes: &[u8]) -> Result<Self, StageError> {
        let text = std::str::from_utf8(bytes).map_err(|e| {
            StageError::new(file, StageErrorKind::Syntax, "", format!("not UTF-8: {e}"))
        })?;
        let stage = StageFile::parse(file, text)?;
        for (name, axis) in stage.axes() {
            if !axis.model.runs_on_firmware() {
                let message = format!(
                    "\"{}\": the firmware runs the static models (symmetric, asymmetric) only",
                    axis.model.name()
                );
                return Err(StageError::new(
                    file,
                    StageErrorKind::Invalid,
                    &format!("{name}.model"),
                    message,
                )
                .located(file, text));
            }
        }
        let valid = stage.validate().map_err(|e| e.located(file, text))?;
        let x = firmware_axis(&stage, &valid.axes[0]);
        let y = valid.axes.get(1).map_or(x, |a| firmware_axis(&stage, a));
        Ok(Self {
            version: format!("{} {}", stage.stage.name, stage.stage.version),
            fnv1a32: fnv1a32(bytes),
            loop_rate_hz: stage.stage.loop_rate_hz,
            io: stage.io.chain(),
            axes: [x, y],
            file: stage,
        })
    }

    /// Whether the file has one axis (whose `x` set drives both channels).
    pub fn one_axis(&self) -> bool {
        self.file.y.is_none()
    }
}

/// A validated static-model axis (a static model has both its Bouc-Wen set and its map: the
/// validation refuses one without).
fn firmware_axis(file: &StageFile, valid: &ValidAxis) -> AxisParams {
    let axis = if valid.name == "x" {
        &file.x
    } else {
        file.y.as_ref().unwrap_or(&file.x)
    };
    let asymmetry = match valid.chain {
        AxisChain::Static { model, .. } => model.asymmetry(),
        _ => Asymmetry::default(),
    };
    AxisParams {
        bouc_wen: axis.bouc_wen.unwrap_or(BoucWenParams {
            a: 0.0,
            beta: 0.0,
            gamma: 0.0,
            n: 1.0,
        }),
        static_map: axis.static_map.unwrap_or(StaticMap {
            k1_m_per_v: 0.0,
            k2_m_per_h: 0.0,
            offset_m: 0.0,
        }),
        asymmetry,
        limits: axis.limits,
        linear_gain_m_per_v: valid.linear_gain_m_per_v,
        rest_output_m: valid.rest_output_m,
        effects: axis.effects,
        servo: axis.servo,
        envelope: axis.envelope(),
        on_target: valid.on_target,
    }
}
