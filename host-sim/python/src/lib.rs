//! The `piezo` Python package: host-sim's stage file, prediction, compensation, identification,
//! close-loop and firmware link, called from Python on NumPy arrays.
//!
//! A thin layer: every number comes from the function the `host-sim` command line calls —
//! `Stage.predict` from `identify::predict::predict_axes` (`host-sim predict`), `Stage.compensate`
//! from `compensate::compensate_stage` (`host-sim compensate`), `identify` from
//! `identify::identify_stage` (`host-sim identify`), `close_loop` from
//! `cl::close_loop_validated` and `cl::stage::stage_file` (`host-sim close-loop`),
//! `Link` from `link::Client` (`host-sim link`). Units are SI throughout (s, V, m), as in the
//! stage file and the records: a one-axis signal is a 1-D array, a two-axis one an N × 2 array
//! (columns x, y). Errors raise `piezo.PiezoError` with the message the command line prints
//! (file, line, column and key for a stage file).

use host_sim::close_loop::{self as cl, CloseLoopSettings};
use host_sim::compensate::{compensate_stage, Reference};
use host_sim::identify::model::ModelKind;
use host_sim::identify::predict::{predict_axes, ReadStage};
use host_sim::identify::{identify_stage, IdentifySettings, Method, Record};
use host_sim::link::{control_mode, model_set_of, upload_set, Client};
use host_sim::stage_file::{stage_text, Verdict};
use numpy::ndarray::{Array2, ArrayViewD, Axis};
use numpy::{AllowTypeChange, IntoPyArray, PyArrayLike1, PyArrayLikeDyn};
use pyo3::create_exception;
use pyo3::exceptions::{PyException, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::sync::mpsc::{self, RecvTimeoutError};
use std::sync::Mutex;
use std::time::{Duration, Instant};

create_exception!(
    piezo,
    PiezoError,
    PyException,
    "An error of the piezo tools: the message host-sim prints (a stage file's errors name the file, line, column and key; a firmware refusal carries the core's reason)."
);

/// Sample times \[s\]: any 1-D array-like, converted to f64.
type Times<'py> = PyArrayLike1<'py, f64, AllowTypeChange>;
/// Samples of one axis (1-D) or two (N × 2): any array-like, converted to f64.
type Samples<'py> = PyArrayLikeDyn<'py, f64, AllowTypeChange>;

fn error(message: impl ToString) -> PyErr {
    PiezoError::new_err(message.to_string())
}

/// A JSON value as Python objects (dicts, lists, floats; `null` as `None`).
fn json_to_py<'py>(py: Python<'py>, value: &Value) -> PyResult<Bound<'py, PyAny>> {
    let text = serde_json::to_string(value).map_err(|e| error(e.to_string()))?;
    py.import("json")?.call_method1("loads", (text,))
}

/// The columns of a 1-D array (one axis) or an N × 1 / N × 2 array (one or two axes).
fn columns(name: &str, a: &ArrayViewD<'_, f64>) -> PyResult<Vec<Vec<f64>>> {
    match a.shape() {
        [_] => Ok(vec![a.iter().copied().collect()]),
        [_, k @ (1 | 2)] => Ok((0..*k)
            .map(|j| a.index_axis(Axis(1), j).iter().copied().collect())
            .collect()),
        shape => Err(PyValueError::new_err(format!(
            "{name}: expected a 1-D array (one axis) or an N x 2 array (two axes: x, y), got shape {shape:?}"
        ))),
    }
}

/// Per-axis columns back into the caller's shape: 1-D for a 1-D input, N × k otherwise.
fn shaped<'py>(
    py: Python<'py>,
    one_d: bool,
    columns: Vec<Vec<f64>>,
) -> PyResult<Bound<'py, PyAny>> {
    if one_d && columns.len() == 1 {
        let column = columns.into_iter().next().unwrap_or_default();
        return Ok(column.into_pyarray(py).into_any());
    }
    let n = columns.first().map_or(0, Vec::len);
    let k = columns.len();
    let array = Array2::from_shape_fn((n, k), |(i, j)| columns[j][i]);
    Ok(array.into_pyarray(py).into_any())
}

/// One record per axis from the arrays `t` (1-D), `u` and `y` (1-D or N × 2), named `name` in
/// messages and reports: equal lengths, at least 10 samples, finite values, `t` increasing.
fn records(name: &str, t: &Times<'_>, u: &Samples<'_>, y: &Samples<'_>) -> PyResult<Vec<Record>> {
    let t: Vec<f64> = t.as_array().to_vec();
    let us = columns("u", &u.as_array())?;
    let ys = columns("y", &y.as_array())?;
    if us.len() != ys.len() {
        return Err(PyValueError::new_err(format!(
            "u has {} axis(es), y {}: give one column per axis in each",
            us.len(),
            ys.len()
        )));
    }
    let n = t.len();
    if n < 10 {
        return Err(PyValueError::new_err(format!(
            "t: {n} samples; at least 10 are needed"
        )));
    }
    for (what, v) in us
        .iter()
        .map(|c| ("u", c))
        .chain(ys.iter().map(|c| ("y", c)))
    {
        if v.len() != n {
            return Err(PyValueError::new_err(format!(
                "{what}: {} samples, t has {n}",
                v.len()
            )));
        }
    }
    for (what, v) in std::iter::once(("t", &t))
        .chain(us.iter().map(|c| ("u", c)))
        .chain(ys.iter().map(|c| ("y", c)))
    {
        if let Some(k) = v.iter().position(|x| !x.is_finite()) {
            return Err(PyValueError::new_err(format!(
                "{what}: sample {k} is not a finite number ({})",
                v[k]
            )));
        }
    }
    if let Some(k) = t.windows(2).position(|w| w[1] <= w[0]) {
        return Err(PyValueError::new_err(format!(
            "t: not increasing at sample {} ({} s after {} s)",
            k + 1,
            t[k + 1],
            t[k]
        )));
    }
    Ok(us
        .into_iter()
        .zip(ys)
        .map(|(u, y)| Record::from_parts(PathBuf::from(name), t.clone(), u, y))
        .collect())
}

/// Runs `work` on a thread of its own while the interpreter waits: every 0.1 s it checks for
/// Ctrl-C (`KeyboardInterrupt` is raised at once; the computation is abandoned and ends on its
/// thread) and every 0.5 s calls `progress(elapsed_s)` when given (an exception it raises stops
/// the wait the same way).
fn run_interruptible<T: Send + 'static>(
    py: Python<'_>,
    progress: Option<&Bound<'_, PyAny>>,
    work: impl FnOnce() -> host_sim::Result<T> + Send + 'static,
) -> PyResult<T> {
    let (tx, mut rx) = mpsc::channel();
    std::thread::spawn(move || {
        let _ = tx.send(work());
    });
    let started = Instant::now();
    let mut reported = Instant::now();
    loop {
        // The receiver goes to the waiting (detached) code and back: it is not `Sync`.
        let (got, back) = py.detach(move || (rx.recv_timeout(Duration::from_millis(100)), rx));
        rx = back;
        match got {
            Ok(result) => return result.map_err(error),
            Err(RecvTimeoutError::Disconnected) => {
                return Err(error(
                    "the computation ended without a result (an internal error; see stderr)",
                ))
            }
            Err(RecvTimeoutError::Timeout) => {}
        }
        py.check_signals()?;
        if let Some(callback) = progress {
            if reported.elapsed() >= Duration::from_millis(500) {
                reported = Instant::now();
                callback.call1((started.elapsed().as_secs_f64(),))?;
            }
        }
    }
}

/// A stage file: `[stage]`, `[io]` and one or two axes (`x`, `y`), validated by the core as
/// `host-sim predict` validates it (every model parameter); `compensate`, `Link.upload` and the
/// firmware further require the firmware's check (static models, invertible maps, windows inside
/// the drive span).
#[pyclass(module = "piezo", frozen)]
pub struct Stage {
    read: ReadStage,
}

impl Stage {
    fn parse(name: String, text: String) -> PyResult<Self> {
        ReadStage::parse(name, text)
            .map(|read| Self { read })
            .map_err(error)
    }

    /// The stage file written by identify/close-loop for `file` (with `header`), as text, and the
    /// firmware's verdict on it.
    fn written(
        name: &str,
        header: &str,
        file: &piezo_stage::StageFile,
    ) -> host_sim::Result<(Self, Verdict)> {
        let (file, text) = stage_text(header, file);
        let verdict = Verdict::of(&file, Path::new(name), None);
        let read = ReadStage::parse(name.to_string(), text)?;
        Ok((Self { read }, verdict))
    }

    fn firmware_valid(&self) -> PyResult<piezo_stage::ValidStage> {
        let r = &self.read;
        r.file
            .validate()
            .map_err(|e| error(e.located(&r.name, &r.text).to_string()))
    }
}

#[pymethods]
impl Stage {
    /// Reads and validates a stage file (TOML); errors name the file, line, column and key.
    #[staticmethod]
    fn load(path: PathBuf) -> PyResult<Self> {
        let name = path.display().to_string();
        let text = std::fs::read_to_string(&path).map_err(|e| error(format!("{name}: {e}")))?;
        Self::parse(name, text)
    }

    /// Parses and validates a stage file's text; `name` is the file named in errors.
    #[staticmethod]
    #[pyo3(signature = (text, name = "<string>"))]
    fn from_toml(text: String, name: &str) -> PyResult<Self> {
        Self::parse(name.to_string(), text)
    }

    /// Writes the stage file's text (as read, comments included) to `path`.
    fn save(&self, path: PathBuf) -> PyResult<()> {
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).map_err(|e| error(format!("{}: {e}", dir.display())))?;
        }
        std::fs::write(&path, &self.read.text)
            .map_err(|e| error(format!("{}: {e}", path.display())))
    }

    /// The stage file's text (TOML).
    fn to_toml(&self) -> &str {
        &self.read.text
    }

    /// The file named in errors.
    #[getter]
    fn name(&self) -> &str {
        &self.read.name
    }

    /// The axes present: `["x"]` or `["x", "y"]`.
    #[getter]
    fn axes(&self) -> Vec<&'static str> {
        self.read.file.axes().into_iter().map(|(n, _)| n).collect()
    }

    /// The loop rate `[stage].loop_rate_hz` \[Hz\].
    #[getter]
    fn loop_rate_hz(&self) -> f32 {
        self.read.file.stage.loop_rate_hz
    }

    /// Every table of the file as a dict (`stage`, `io`, `x`, `y`), SI units as in the file.
    #[getter]
    fn params<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let value = serde_json::to_value(&self.read.file).map_err(|e| error(e.to_string()))?;
        json_to_py(py, &value)
    }

    /// Why the firmware's check would refuse the file (located), or None when it accepts it.
    fn firmware_refusal(&self) -> Option<String> {
        self.read.firmware_refusal()
    }

    /// The stage's output \[m\] for the stack voltages `u` \[V\] (1-D for one axis, N × 2 for
    /// two), as `host-sim predict` runs the chain: the firmware's models and effects, from rest at
    /// the first input, at the sample period of `t` \[s\] (default: the loop period).
    #[pyo3(signature = (u, t = None))]
    fn predict<'py>(
        &self,
        py: Python<'py>,
        u: Samples<'py>,
        t: Option<Times<'py>>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let u_view = u.as_array();
        let one_d = u_view.ndim() == 1;
        let us = columns("u", &u_view)?;
        let n = us[0].len();
        if n < 2 {
            return Err(PyValueError::new_err("u: at least 2 samples are needed"));
        }
        let t: Vec<f64> = match t {
            Some(t) => t.as_array().to_vec(),
            None => {
                let rate = f64::from(self.read.file.stage.loop_rate_hz);
                (0..n).map(|k| k as f64 / rate).collect()
            }
        };
        if t.len() != n {
            return Err(PyValueError::new_err(format!(
                "t: {} samples, u has {n}",
                t.len()
            )));
        }
        let records: Vec<Record> = us
            .into_iter()
            .map(|u| Record::from_parts(PathBuf::from("u"), t.clone(), u, vec![0.0; n]))
            .collect();
        let predicted = predict_axes(&self.read, &records, 0).map_err(error)?;
        shaped(
            py,
            one_d,
            predicted.into_iter().map(|p| p.predicted_m).collect(),
        )
    }

    /// The stack voltages \[V\] the firmware commands for the reference `r` \[m\] (1-D for one
    /// axis, N × 2 for two) sampled at the loop rate, as `host-sim compensate` computes them (the
    /// firmware's inverse chain, from rest); `periodic`: `r` is one period of a reference played
    /// in a loop, the period the compensator settles to (as `learn --periodic`).
    #[pyo3(signature = (r, periodic = false))]
    fn compensate<'py>(
        &self,
        py: Python<'py>,
        r: Samples<'py>,
        periodic: bool,
    ) -> PyResult<Bound<'py, PyAny>> {
        let valid = self.firmware_valid()?;
        let r_view = r.as_array();
        let one_d = r_view.ndim() == 1;
        let rs = columns("r", &r_view)?;
        let n = rs[0].len();
        if n < 2 {
            return Err(PyValueError::new_err("r: at least 2 samples are needed"));
        }
        let names: &[&str] = if rs.len() == 1 {
            &["r_m"]
        } else {
            &["rx_m", "ry_m"]
        };
        let mut axes = Vec::new();
        for (name, column) in names.iter().zip(&rs) {
            if let Some(k) = column.iter().position(|v| !(*v as f32).is_finite()) {
                return Err(PyValueError::new_err(format!(
                    "r: sample {k} of {name} is not a finite number in f32 ({})",
                    column[k]
                )));
            }
            axes.push((
                name.to_string(),
                column.iter().map(|&v| v as f32).collect::<Vec<f32>>(),
            ));
        }
        let rate = f64::from(self.read.file.stage.loop_rate_hz);
        let reference = Reference {
            t_s: (0..n).map(|k| k as f64 / rate).collect(),
            lines: (0..n).collect(),
            axes,
        };
        let r = &self.read;
        let result = compensate_stage(
            &r.file,
            &valid,
            (Path::new(&r.name), &r.text),
            Path::new("the reference array (lines are its rows)"),
            &reference,
            periodic,
        )
        .map_err(error)?;
        shaped(
            py,
            one_d,
            result
                .voltages_v
                .into_iter()
                .map(|(_, u)| u.into_iter().map(f64::from).collect())
                .collect(),
        )
    }

    fn __repr__(&self) -> String {
        let f = &self.read.file;
        format!(
            "Stage({:?}, axes={:?}, loop_rate_hz={}, models={:?})",
            self.read.name,
            self.axes(),
            f.stage.loop_rate_hz,
            f.axes()
                .iter()
                .map(|(_, a)| a.model.name())
                .collect::<Vec<_>>()
        )
    }
}

fn parse_enum<T: clap::ValueEnum>(what: &str, value: &str) -> PyResult<T> {
    T::from_str(value, false).map_err(|_| {
        let names: Vec<String> = T::value_variants()
            .iter()
            .filter_map(|v| v.to_possible_value().map(|p| p.get_name().to_string()))
            .collect();
        PyValueError::new_err(format!(
            "{what} {value:?}: expected one of {}",
            names.join(", ")
        ))
    })
}

/// The `[stage]` and `[io]` of a given stage.
fn given_of(stage: Option<&Bound<'_, Stage>>) -> Option<(piezo_stage::Stage, piezo_stage::Io)> {
    stage.map(|s| {
        let file = &s.get().read.file;
        (file.stage.clone(), file.io.clone())
    })
}

/// Merges the keys of `extra` (an object) into `report` (an object).
fn merged(mut report: Value, extra: Value) -> Value {
    if let (Some(r), Value::Object(e)) = (report.as_object_mut(), extra) {
        r.extend(e);
    }
    report
}

/// Fits a model to a record and returns `(Stage, report)`, as `host-sim identify` does (the
/// stage file it writes, the report JSON as a dict).
#[pyfunction]
#[pyo3(signature = (t, u, y, model, *, method = "vp-de-lm", invertible = false, stage = None, start = 0.0, seed = 1, no_shift = false, progress = None, name = "arrays"))]
#[allow(clippy::too_many_arguments)]
fn identify<'py>(
    py: Python<'py>,
    t: Times<'py>,
    u: Samples<'py>,
    y: Samples<'py>,
    model: &str,
    method: &str,
    invertible: bool,
    stage: Option<Bound<'py, Stage>>,
    start: f64,
    seed: u64,
    no_shift: bool,
    progress: Option<Bound<'py, PyAny>>,
    name: &str,
) -> PyResult<(Stage, Bound<'py, PyAny>)> {
    let records = records(name, &t, &u, &y)?;
    let settings = IdentifySettings {
        model: parse_enum::<ModelKind>("model", model)?,
        method: parse_enum::<Method>("method", method)?,
        seed,
        start_s: start,
        no_shift,
        invertible,
        free_offset: false,
        progress: false,
    };
    let given = given_of(stage.as_ref());
    let name = name.to_string();
    let (stage, report) = run_interruptible(py, progress.as_ref(), move || {
        let identified = identify_stage(&records, &settings, None, given, &name)?;
        let (stage, verdict) = Stage::written(&name, &identified.header, &identified.file)?;
        let report = merged(
            identified.report()?,
            host_sim::to_json(&verdict.report(invertible, None))?,
        );
        Ok((stage, report))
    })?;
    Ok((stage, json_to_py(py, &report)?))
}

/// Fits the base model, finds the effects its residual lacks, adds them and refits, as
/// `host-sim close-loop` does; returns `(Stage, report)` (the stage file it writes, the report
/// JSON as a dict). `validate`: another record `(t, u, y)` both models must predict.
#[pyfunction]
#[pyo3(signature = (t, u, y, *, start = 0.0, min_share = 0.05, seed = 1, invertible = false, stage = None, validate = None, validate_start = 0.0, progress = None, name = "arrays"))]
#[allow(clippy::too_many_arguments)]
fn close_loop<'py>(
    py: Python<'py>,
    t: Times<'py>,
    u: Samples<'py>,
    y: Samples<'py>,
    start: f64,
    min_share: f64,
    seed: u64,
    invertible: bool,
    stage: Option<Bound<'py, Stage>>,
    validate: Option<(Times<'py>, Samples<'py>, Samples<'py>)>,
    validate_start: f64,
    progress: Option<Bound<'py, PyAny>>,
    name: &str,
) -> PyResult<(Stage, Bound<'py, PyAny>)> {
    if !(min_share > 0.0 && min_share < 1.0) {
        return Err(PyValueError::new_err(format!(
            "min_share {min_share}: must be in (0, 1)"
        )));
    }
    let records = records(name, &t, &u, &y)?;
    let validation = match &validate {
        Some((t, u, y)) => {
            let v = self::records("validate", t, u, y)?;
            if v.len() != records.len() {
                return Err(PyValueError::new_err(format!(
                    "validate: {} axes, the record has {}",
                    v.len(),
                    records.len()
                )));
            }
            Some(v)
        }
        None => None,
    };
    let given = given_of(stage.as_ref());
    let name = name.to_string();
    let (stage, report) = run_interruptible(py, progress.as_ref(), move || {
        let (stage, io) = match given {
            Some(given) => given,
            None => cl::stage_and_io_for(&records, Path::new(&name), None)?,
        };
        let settings = CloseLoopSettings {
            start_s: start,
            min_share,
            seed,
            invertible,
            whole_set_invertible: invertible,
            loop_rate_hz: Some(stage.loop_rate_hz),
            ..Default::default()
        };
        let started = Instant::now();
        let outcome = cl::close_loop_validated(
            &records,
            &settings,
            validation.as_deref().map(|v| (v, validate_start)),
        )
        .map_err(host_sim::Error::from)?;
        let file = cl::stage::stage_file(&outcome, &name, stage, io)?;
        let header = cl::stage::header(&outcome, &name);
        let (stage, verdict) = Stage::written(&name, &header, &file)?;
        let mut report = merged(
            host_sim::to_json(&outcome.report())?,
            host_sim::to_json(&verdict.report(invertible, None))?,
        );
        report["seconds"] = started.elapsed().as_secs_f64().into();
        Ok((stage, report))
    })?;
    Ok((stage, json_to_py(py, &report)?))
}

/// A connection to the firmware's command link (`tcp:HOST:PORT` for the QEMU image,
/// `serial:PATH` for the board), as `host-sim link` drives it; a context manager that closes the
/// connection on exit. Every answer waits at most `timeout` seconds; `wait` waits that long for
/// a firmware that is still starting.
#[pyclass(module = "piezo", frozen)]
pub struct Link {
    client: Mutex<Option<Client>>,
}

/// One `excite` or `track` run's arguments.
struct Run<'a> {
    signal: &'a str,
    duration: f64,
    decimation: u32,
    allow_gaps: bool,
    /// `track` (reference columns, scored) rather than `excite`.
    tracking: bool,
    /// Where to draw the record, if anywhere.
    plot: Option<PathBuf>,
}

impl Link {
    fn with<T: Send>(
        &self,
        py: Python<'_>,
        f: impl FnOnce(&mut Client) -> host_sim::Result<T> + Send,
    ) -> PyResult<T> {
        py.detach(|| {
            let mut guard = self.client.lock().map_err(|_| {
                host_sim::Error::Link("the link was poisoned by an earlier failure".into())
            })?;
            let client = guard
                .as_mut()
                .ok_or_else(|| host_sim::Error::Link("the link is closed".into()))?;
            f(client)
        })
        .map_err(error)
    }

    fn run<'py>(&self, py: Python<'py>, run: Run<'_>) -> PyResult<Bound<'py, PyDict>> {
        let Run {
            signal,
            duration,
            decimation,
            allow_gaps,
            tracking,
            plot,
        } = run;
        if let Some(path) = &plot {
            host_sim::track_plot::check_plot_path("plot", path).map_err(error)?;
        }
        let table = self.with(py, |c| {
            let recording = c.run(signal, duration, decimation, !tracking)?;
            recording.check_gaps(allow_gaps)?;
            let columns = recording.columns(tracking);
            if let Some(path) = &plot {
                host_sim::link::plot_record(path, &columns, tracking)?;
            }
            Ok(columns.to_table())
        })?;
        let out = PyDict::new(py);
        for (name, column) in table.names.into_iter().zip(table.columns) {
            out.set_item(name, column.into_pyarray(py))?;
        }
        Ok(out)
    }
}

#[pymethods]
impl Link {
    #[new]
    #[pyo3(signature = (connect, timeout = 10.0, wait = 0.0))]
    fn new(py: Python<'_>, connect: &str, timeout: f64, wait: f64) -> PyResult<Self> {
        if !(timeout > 0.0 && timeout.is_finite()) {
            return Err(PyValueError::new_err("timeout must be > 0"));
        }
        if !(wait >= 0.0 && wait.is_finite()) {
            return Err(PyValueError::new_err("wait must be >= 0"));
        }
        let timeout = Duration::from_secs_f64(timeout);
        let client = py
            .detach(|| {
                if wait > 0.0 {
                    Client::connect_waiting(connect, timeout, Duration::from_secs_f64(wait))
                } else {
                    Client::connect(connect, timeout)
                }
            })
            .map_err(error)?;
        Ok(Self {
            client: Mutex::new(Some(client)),
        })
    }

    fn __enter__(slf: Py<Self>) -> Py<Self> {
        slf
    }

    #[pyo3(signature = (*_args))]
    fn __exit__(&self, _args: &Bound<'_, pyo3::types::PyTuple>) -> bool {
        self.close();
        false
    }

    /// Closes the connection (later calls raise).
    fn close(&self) {
        if let Ok(mut guard) = self.client.lock() {
            guard.take();
        }
    }

    /// The firmware's state as a dict (`host-sim link status`).
    fn status<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let status = self.with(py, |c| c.status())?;
        let value = serde_json::to_value(status).map_err(|e| error(e.to_string()))?;
        json_to_py(py, &value)
    }

    /// Open-loop excitation in stack volts: plays `signal` (host-sim's signal grammar, volts) for
    /// `duration` seconds and returns the record as a dict of arrays named as the CSV's columns
    /// (`t_s`, `ux_V`, `uy_V`, `x_m`, `y_m`). `plot` (`.png` or `.svg`) also draws it, as
    /// `host-sim link excite --plot` does.
    #[pyo3(signature = (signal, duration, decimation = 1, allow_gaps = false, plot = None))]
    fn excite<'py>(
        &self,
        py: Python<'py>,
        signal: &str,
        duration: f64,
        decimation: u32,
        allow_gaps: bool,
        plot: Option<PathBuf>,
    ) -> PyResult<Bound<'py, PyDict>> {
        let run = Run {
            signal,
            duration,
            decimation,
            allow_gaps,
            tracking: false,
            plot,
        };
        self.run(py, run)
    }

    /// Tracks `signal` (metres) in the current control mode for `duration` seconds; the record
    /// as `excite`'s plus `rx_m`, `ry_m`. `plot` (`.png` or `.svg`) also draws it as `host-sim link
    /// track --plot` does: sensor against reference, scored from 0.1 s on.
    #[pyo3(signature = (signal, duration, decimation = 1, allow_gaps = false, plot = None))]
    fn track<'py>(
        &self,
        py: Python<'py>,
        signal: &str,
        duration: f64,
        decimation: u32,
        allow_gaps: bool,
        plot: Option<PathBuf>,
    ) -> PyResult<Bound<'py, PyDict>> {
        let run = Run {
            signal,
            duration,
            decimation,
            allow_gaps,
            tracking: true,
            plot,
        };
        self.run(py, run)
    }

    /// Sends the stage's model to the firmware; returns the checksum it loaded. A refusal raises
    /// with the core's reason.
    fn upload(&self, py: Python<'_>, stage: &Bound<'_, Stage>) -> PyResult<u32> {
        let stage = stage.get();
        stage.firmware_valid()?;
        let r = &stage.read;
        let path = Path::new(&r.name);
        let set = model_set_of(path, r.text.as_bytes()).map_err(error)?;
        self.with(py, |c| upload_set(c, set, path))
    }

    /// Switches the control mode of `track` (`open-loop`, `feedforward`, `feedback`,
    /// `feedforward+feedback`, `learned`, `learned+feedback`); returns the firmware's answer.
    fn control<'py>(&self, py: Python<'py>, mode: &str) -> PyResult<Bound<'py, PyAny>> {
        let control = control_mode(mode).map_err(|e| PyValueError::new_err(e.to_string()))?;
        self.request(py, piezo_link::Request::Control(control))
    }

    /// Leaves the safe state; returns the firmware's answer.
    fn rearm<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        self.request(py, piezo_link::Request::Rearm)
    }

    /// Ends the firmware's run (the QEMU image exits).
    fn shutdown<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        self.request(py, piezo_link::Request::Shutdown)
    }
}

impl Link {
    fn request<'py>(
        &self,
        py: Python<'py>,
        request: piezo_link::Request,
    ) -> PyResult<Bound<'py, PyAny>> {
        let response = self.with(py, |c| c.expect(request))?;
        let value = serde_json::to_value(response).map_err(|e| error(e.to_string()))?;
        json_to_py(py, &value)
    }
}

/// The `piezo` module.
#[pymodule]
fn piezo(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("PiezoError", m.py().get_type::<PiezoError>())?;
    m.add_class::<Stage>()?;
    m.add_class::<Link>()?;
    m.add_function(wrap_pyfunction!(identify, m)?)?;
    m.add_function(wrap_pyfunction!(close_loop, m)?)?;
    Ok(())
}
