//! `host-sim link step`: a move to a position and its settling time, over the command link.
//!
//! ```text
//! host-sim link --connect ADDR step --to X[,Y] [--tolerance T] [--timeout S] [--frames CSV]
//! ```
//!
//! The firmware tracks a constant reference (`Program::PerAxis` of `Wave::Constant`, metres, as
//! `link track` takes positions) with every frame sent (decimation 1), until both axes are on
//! target or `--timeout` seconds of the loop's time have passed. On target is the firmware's rule
//! (`piezo_core::on_target`): frame k's reading against the reference of frame k − 1,
//! |y\[k\] − r\[k−1\]| ≤ tolerance for N consecutive ticks. The host evaluates it on the frames
//! with the same core code (N the firmware's, the tolerance `--tolerance` or the firmware's
//! band), and also reads the firmware's own flags (frame `flags` bits 2 and 3) and its `status`.
//! The settling time is the ticks from the first reading that answers the new reference to the
//! first tick of the in-band run that set the flag, × T (the firmware's `settle_ticks`).

use crate::link::{run_limits, Client};
use piezo_core::on_target::NOT_SETTLED;
use piezo_core::{OnTarget, OnTargetState};
use piezo_link::{Frame, Program, Request, Response, Wave};
use std::io::Write;
use std::path::PathBuf;

/// Arguments of `link step`.
#[derive(Debug, clap::Args)]
pub struct StepArgs {
    /// Where to go (m): one value for both axes or `X,Y`.
    #[arg(long)]
    pub to: String,
    /// On-target band (m) the host times the move with (default: the firmware's band, from
    /// its stage file's `[x.on_target]`).
    #[arg(long)]
    pub tolerance: Option<f64>,
    /// Longest wait for both axes on target, in the loop's time (s).
    #[arg(long, default_value_t = 1.0)]
    pub timeout: f64,
    /// Also write every frame of the move (CSV: sequence, rx_m, ry_m, ux_V, uy_V, x_m, y_m,
    /// flags).
    #[arg(long)]
    pub frames: Option<PathBuf>,
}

/// Runs `link step`: JSON on stdout; an error when an axis is not on target in time.
pub fn link_step_cmd(client: &mut Client, a: &StepArgs) -> crate::Result<String> {
    let to = crate::settle::parse_pair("--to", &a.to)?;
    let status = client.status()?;
    let (rate, _) = run_limits(&status)?;
    if !(a.timeout > 0.0 && a.timeout * rate <= 1e8) {
        return Err(crate::Error::Link(format!(
            "--timeout {}: expected > 0 s and at most 1e8 ticks",
            a.timeout
        )));
    }
    let max_frames = (a.timeout * rate).ceil() as usize;
    let device_band = status.on_target.map(|b| (b.tolerance_m, b.ticks));
    let bands = device_band
        .map(|(t, n)| OnTarget::new(a.tolerance.map_or(t, |t| t as f32), n))
        .map(|b| {
            b.map_err(|e| {
                crate::Error::Link(format!(
                    "--tolerance: {e} (the firmware's band: {device_band:?})"
                ))
            })
        });
    let [bx, by] = bands;
    let bands = [bx?, by?];

    client.expect(Request::Frames { decimation: 1 })?;
    let program = Program::PerAxis(to.map(|offset| Wave::Constant { offset }));
    let first = match client.expect(Request::Track(program))? {
        Response::Started { first_frame } => first_frame,
        other => {
            return Err(crate::Error::Link(format!(
                "unexpected answer to a program: {other:?}"
            )))
        }
    };
    let mut host = [OnTargetState::default(); 2];
    let mut previous_reference: Option<[f32; 2]> = None;
    let mut host_flag = [None::<usize>; 2];
    let mut device_flag = [None::<usize>; 2];
    let mut count = 0usize;
    let frames = client.frames_through(|f: &Frame| {
        // Frames of the program only (earlier ones are the previous hold's).
        if f.sequence.wrapping_sub(first) >= u32::MAX / 2 {
            return false;
        }
        let k = count;
        count += 1;
        if let Some(r) = previous_reference {
            for i in 0..2 {
                if bands[i].observe(&mut host[i], f.sensor_m[i], r[i]) && host_flag[i].is_none() {
                    host_flag[i] = Some(k);
                }
            }
        }
        previous_reference = Some(f.reference_m);
        for (i, flag) in device_flag.iter_mut().enumerate() {
            if f.flags & Frame::on_target_flag(i) != 0 && k > 0 && flag.is_none() {
                *flag = Some(k);
            }
        }
        let done = host_flag.iter().all(Option::is_some) && device_flag.iter().all(Option::is_some);
        done || count >= max_frames
    })?;
    client.expect(Request::Frames { decimation: 0 })?;
    client.take_frames();
    let after = client.status()?;
    let frames: Vec<Frame> = frames
        .into_iter()
        .filter(|f| f.sequence.wrapping_sub(first) < u32::MAX / 2)
        .collect();
    if let Some(path) = &a.frames {
        write_frames(path, &frames)?;
    }
    let settle = host.map(|s| {
        let t = s.settle_ticks();
        (t != NOT_SETTLED).then_some(t)
    });
    // Host ticks count from frame 1 (the first reading that answers the new reference).
    let settle = [0, 1].map(|i| host_flag[i].and(settle[i]));
    let seconds = |t: Option<u32>| t.map(|t| f64::from(t) / rate);
    let ticks_of = |k: Option<usize>| k.map(|k| k.saturating_sub(1) as u32);
    let value = serde_json::json!({
        "to_m": to,
        "loop_rate_hz": rate,
        "tolerance_m": bands.map(|b| b.tolerance_m),
        "ticks": bands.map(|b| b.ticks),
        "settle_ticks": settle,
        "settle_s": settle.map(seconds),
        "on_target_ticks": host_flag.map(ticks_of),
        "device_on_target_ticks": device_flag.map(ticks_of),
        "frames": frames.len(),
        "first_frame": first,
        "final_error_m": frames.last().map(|f| [0, 1].map(|i| f.sensor_m[i] - f.reference_m[i])),
        "on_target": after.on_target,
        "mode": after.mode,
        "counters": after.counters,
    });
    if settle.iter().any(Option::is_none) {
        return Err(crate::Error::Link(format!(
            "not on target within --timeout {} s: {value}",
            a.timeout
        )));
    }
    serde_json::to_string(&value).map_err(crate::Error::from)
}

fn write_frames(path: &std::path::Path, frames: &[Frame]) -> crate::Result<()> {
    let name = path.display();
    let mut out = String::from("sequence,rx_m,ry_m,ux_V,uy_V,x_m,y_m,flags\n");
    for f in frames {
        out.push_str(&format!(
            "{},{:e},{:e},{},{},{:e},{:e},{}\n",
            f.sequence,
            f.reference_m[0],
            f.reference_m[1],
            f.commanded_v[0],
            f.commanded_v[1],
            f.sensor_m[0],
            f.sensor_m[1],
            f.flags
        ));
    }
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(|e| crate::Error::Link(format!("{name}: {e}")))?;
    }
    std::fs::File::create(path)
        .and_then(|mut f| f.write_all(out.as_bytes()))
        .map_err(|e| crate::Error::Link(format!("{name}: {e}")))
}
