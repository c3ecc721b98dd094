//! Which set a stage file is, said the way the firmware says which set it runs.
//!
//! The firmware's boot line names its set as `parameters <version> (<file>), fnv1a32 0x<hash>,
//! fingerprint 0x<hash>, loop <rate> Hz`, and `link status` carries the same three values as
//! `params_version`, `params_fnv1a32` and `params_fingerprint`. [`SetIdentity`] computes them on the
//! host from a stage file: the version `name version` of its `[stage]`, FNV-1a 32 of its bytes
//! (`piezo_stage::fnv1a32`, what the build and an upload say), and the fingerprint of the set the
//! firmware would run (`piezo_link::ModelSet::fingerprint`, of the loop rate, io chain and axes:
//! derived from the content, so two files that drive the stage alike share it). `predict`,
//! `identify` and `close-loop` print it, so a prediction names the set it ran and a record of the
//! firmware can be matched to the file it came from. A set the firmware refuses has no
//! fingerprint: the line leaves it out, as a boot line without one does.

use std::fmt;
use std::path::Path;

/// The version, file hash and content fingerprint of a stage file. Serialised as a report's
/// fields, named and written as `link status` writes them: `params_version`, `params_fnv1a32` and
/// `params_fingerprint` (`0x` and 8 hex digits; null without one).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct SetIdentity {
    /// The file, as named.
    #[serde(skip)]
    pub file: String,
    /// `name version` of its `[stage]` (the firmware's `params_version`).
    #[serde(rename = "params_version")]
    pub version: String,
    /// FNV-1a 32 of the file's bytes (`params_fnv1a32`).
    #[serde(rename = "params_fnv1a32", serialize_with = "hex32")]
    pub fnv1a32: u32,
    /// The content fingerprint of the set the firmware builds from it (`params_fingerprint`);
    /// `None` when the firmware would refuse the file.
    #[serde(rename = "params_fingerprint", serialize_with = "hex32_or_null")]
    pub fingerprint: Option<u32>,
    /// `[stage] loop_rate_hz` \[Hz\].
    #[serde(skip)]
    pub loop_rate_hz: f32,
}

/// A hash as [`crate::link::hex32`] writes it.
fn hex32<S: serde::Serializer>(value: &u32, s: S) -> Result<S::Ok, S::Error> {
    s.serialize_str(&crate::link::hex32(*value))
}

/// A hash as [`crate::link::hex32`] writes it, or null.
fn hex32_or_null<S: serde::Serializer>(value: &Option<u32>, s: S) -> Result<S::Ok, S::Error> {
    match value {
        Some(value) => hex32(value, s),
        None => s.serialize_none(),
    }
}

impl SetIdentity {
    /// The identity of the stage file at `path`.
    pub fn of_file(path: &Path) -> crate::Result<Self> {
        let bytes = std::fs::read(path).map_err(crate::Error::read("", path))?;
        Self::of_bytes(path, &bytes)
    }

    /// The identity of the stage file `bytes`, read from `path` (named in the line and in errors).
    pub fn of_bytes(path: &Path, bytes: &[u8]) -> crate::Result<Self> {
        let file = path.display().to_string();
        let fnv1a32 = piezo_stage::fnv1a32(bytes);
        match piezo_stage::FirmwareSet::from_bytes(&file, bytes) {
            Ok(set) => Ok(Self {
                version: set.version,
                fnv1a32,
                fingerprint: Some(crate::link::model_set_of(path, bytes)?.fingerprint()),
                loop_rate_hz: set.loop_rate_hz,
                file,
            }),
            Err(_) => {
                let text = std::str::from_utf8(bytes)
                    .map_err(|e| crate::Error::Usage(format!("{file}: {e}")))?;
                let stage = piezo_stage::StageFile::parse(&file, text)
                    .map_err(crate::Error::from)?
                    .stage;
                Ok(Self {
                    version: format!("{} {}", stage.name, stage.version),
                    fnv1a32,
                    fingerprint: None,
                    loop_rate_hz: stage.loop_rate_hz,
                    file,
                })
            }
        }
    }
}

/// The boot line's words: `parameters <version> (<file>), fnv1a32 0x…, fingerprint 0x…, loop
/// <rate> Hz` (without the fingerprint when there is none).
impl fmt::Display for SetIdentity {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "parameters {} ({}), fnv1a32 {}",
            self.version,
            self.file,
            crate::link::hex32(self.fnv1a32)
        )?;
        if let Some(fingerprint) = self.fingerprint {
            write!(f, ", fingerprint {}", crate::link::hex32(fingerprint))?;
        }
        write!(f, ", loop {} Hz", self.loop_rate_hz)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::capture::parse_boot_line;
    use std::path::PathBuf;

    fn xy_stage() -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../firmware/params/xy-stage.toml")
    }

    /// The line reads back as a boot line (capture's parser) with the values `link upload`
    /// prints for the same file: one format for the version, the hash and the fingerprint.
    #[test]
    fn a_stage_file_is_named_as_the_firmware_names_its_set() {
        let path = xy_stage();
        let bytes = std::fs::read(&path).unwrap();
        let id = SetIdentity::of_file(&path).unwrap();
        let set = crate::link::model_set(&path).unwrap();
        let line = id.to_string();
        let boot = parse_boot_line(&format!("piezo-firmware qemu: {line}"), 1)
            .unwrap()
            .unwrap();
        assert_eq!(boot.version, "xy-stage 4", "{line}");
        assert_eq!(
            boot.fnv1a32,
            crate::link::hex32(piezo_stage::fnv1a32(&bytes))
        );
        assert_eq!(
            boot.fingerprint,
            Some(crate::link::hex32(set.fingerprint())),
            "{line}"
        );
        assert_eq!(boot.loop_rate_hz, 20_000.0);
        assert!(line.contains(&path.display().to_string()), "{line}");
        let json = crate::to_json(&id).unwrap();
        assert_eq!(json["params_version"], set.version.as_str());
        assert_eq!(json["params_fingerprint"], boot.fingerprint.unwrap());
        assert_eq!(json["params_fnv1a32"], boot.fnv1a32);
    }

    /// Serialised, a set's identity is the three fields `link status` writes, and no others.
    #[test]
    fn an_identity_serialises_as_the_three_fields_of_link_status() {
        let id = SetIdentity {
            file: "stage.toml".into(),
            version: "xy-stage 4".into(),
            fnv1a32: 0x0012_abcd,
            fingerprint: Some(0xdead_beef),
            loop_rate_hz: 20_000.0,
        };
        let json = crate::to_json(&id).unwrap();
        assert_eq!(
            json,
            serde_json::json!({
                "params_version": "xy-stage 4",
                "params_fnv1a32": "0x0012abcd",
                "params_fingerprint": "0xdeadbeef",
            })
        );
        let refused = SetIdentity {
            fingerprint: None,
            ..id
        };
        let json = crate::to_json(&refused).unwrap();
        assert_eq!(json["params_fingerprint"], serde_json::Value::Null);
        assert_eq!(json.as_object().map(|m| m.len()), Some(3));
    }

    /// `identify` and `close-loop` name the file they wrote by the same line; nothing for a file
    /// not written.
    #[test]
    fn a_written_stage_file_is_named_by_its_identity() {
        let path = xy_stage();
        let mut written = crate::stage_file::WrittenStage {
            path: path.display().to_string(),
            not_written: None,
            verdict: crate::stage_file::Verdict::Accepted,
        };
        let id = SetIdentity::of_file(&path).unwrap();
        assert_eq!(written.identity_line(), format!("\nstage file: {id}"));
        written.not_written = Some("read-only".into());
        assert_eq!(written.identity_line(), "");
    }

    /// A comment changes the file's hash, not the set it drives; a number changes both. A set the
    /// firmware refuses has no fingerprint, and its line still reads as a boot line.
    #[test]
    fn the_fingerprint_follows_the_content_and_the_hash_the_bytes() {
        let path = xy_stage();
        let text = std::fs::read_to_string(&path).unwrap();
        let id = |t: &str| SetIdentity::of_bytes(&path, t.as_bytes()).unwrap();
        let base = id(&text);
        let commented = id(&format!("# another comment\n{text}"));
        assert_ne!(commented.fnv1a32, base.fnv1a32);
        assert_eq!(commented.fingerprint, base.fingerprint);
        let slower = id(&text.replace("loop_rate_hz = 20000.0", "loop_rate_hz = 10000.0"));
        assert!(slower.fingerprint.is_some());
        assert_ne!(slower.fingerprint, base.fingerprint);
        // A stroke of 38 pm (metres written as micrometres): refused by the check the firmware's
        // build makes (piezo-stage's `FirmwareSet::from_bytes`), naming the key and the bounds.
        let tiny: String = text
            .lines()
            .map(|l| match l.split_once(" = ") {
                Some((key @ ("k1_m_per_v" | "k2_m_per_h"), v)) => {
                    format!("{key} = {:e}\n", v.parse::<f64>().unwrap() * 1e-6)
                }
                _ => format!("{l}\n"),
            })
            .collect();
        let e = piezo_stage::FirmwareSet::from_bytes("tiny.toml", tiny.as_bytes()).unwrap_err();
        let e = e.to_string();
        assert!(
            e.contains("k1_m_per_v") && e.contains("outside the 1e-8–1e-2 m"),
            "{e}"
        );
        assert_eq!(id(&tiny).fingerprint, None);
        let refused = id(&text.replace("dac_range_v = [0.0, 5.0]", "dac_range_v = [0.0, 1.0]"));
        assert_eq!(refused.fingerprint, None);
        assert_eq!(refused.version, "xy-stage 4");
        let boot = parse_boot_line(&refused.to_string(), 1).unwrap().unwrap();
        assert_eq!(boot.fingerprint, None);
        assert!(crate::to_json(&refused).unwrap()["params_fingerprint"].is_null());
    }
}
