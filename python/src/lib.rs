//! `ocellus._ocellus`: the native half of the Python package. It loads and runs graphs with the
//! Rust engine and hands values to `ocellus/__init__.py` as tagged tuples of raw bytes, which
//! that module turns into NumPy arrays and dicts (so this crate needs no NumPy headers, and one
//! abi3 wheel serves every CPython ≥ 3.9).
//!
//! Tagged forms (all numbers little-endian):
//!
//! | value | tuple |
//! |-------|-------|
//! | Image | `("image", bytes, height, width, channels, dtype)`, dtype `"u8"`, `"u16"` or `"f32"` |
//! | Keypoints | `("keypoints", bytes)`: records of `f32 x, y, size, angle, response, i32 octave` |
//! | Matches | `("matches", bytes)`: records of `u32 query, u32 train, f32 distance` |
//! | Descriptors | `("descriptors", "float" \| "binary", bytes, rows, cols)` |
//! | Matrix | `("matrix", bytes, rows, cols)`: f64, row-major |
//! | Points2D | `("points2d", bytes, n)`: f64 pairs |
//! | PointCloud | `("point_cloud", positions, n, colors or None, normals or None)` |
//! | Mesh | `("mesh", positions, n, triangles, m, normals, uvs, colors, tangents)` (None when absent) |
//! | Reconstruction | `("reconstruction", cameras, images, points)` (see [`reconstruction`]) |
//! | List | `("list", [tagged…])` |
//! | anything else | `("json", text)`: exactly what `ocellus run --emit` writes |

#![allow(unsafe_code)] // PyO3's macros expand to FFI glue.

use std::path::PathBuf;
use std::sync::{Arc, Mutex};

use ocellus_engine::distribute::{Distribution, Stage, TaskDone, TaskRunner};
use ocellus_engine::{Diagnostics, Graph, Override, Registry, RunOptions, Value};
use pyo3::create_exception;
use pyo3::exceptions::{PyException, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyBytes, PyDict, PyList, PyTuple};

create_exception!(
    _ocellus,
    GraphError,
    PyException,
    "A graph file or a parameter override is invalid; `diagnostics` holds each problem."
);
create_exception!(
    _ocellus,
    RunError,
    PyException,
    "A node failed while running; `failures` holds each failed node."
);
create_exception!(
    _ocellus,
    TaskError,
    PyException,
    "A distributed task could not run on this worker."
);

fn registry(plugins: &[PathBuf]) -> PyResult<Registry> {
    let mut registry = ocellus_nodes::builtin_registry()
        .map_err(|e| PyException::new_err(format!("operator registry: {e}")))?;
    for path in plugins {
        ocellus_engine::load_plugin(path, &mut registry)
            .map_err(|e| GraphError::new_err(format!("plugin {}: {e}", path.display())))?;
    }
    Ok(registry)
}

/// A `GraphError` whose message is the `file:line:col: message` lines and whose `diagnostics`
/// attribute lists them as dicts.
fn graph_error(py: Python<'_>, diags: &Diagnostics) -> PyErr {
    let lines: Vec<String> = diags
        .0
        .iter()
        .map(|d| {
            let at = d.location().map(|l| format!("{l}: ")).unwrap_or_default();
            match &d.help {
                Some(help) => format!("{at}{} (help: {help})", d.message),
                None => format!("{at}{}", d.message),
            }
        })
        .collect();
    let err = GraphError::new_err(lines.join("\n"));
    let list = PyList::empty(py);
    for d in &diags.0 {
        let item = PyDict::new(py);
        let _ = item.set_item("location", d.location());
        let _ = item.set_item("message", &d.message);
        let _ = item.set_item("code", d.code.as_str());
        let _ = item.set_item("help", d.help.clone());
        let _ = list.append(item);
    }
    let _ = err.value(py).setattr("diagnostics", list);
    err
}

/// A loaded, checked graph (the native object behind `ocellus.Graph`).
#[pyclass(module = "ocellus._ocellus", name = "Graph", frozen)]
struct PyGraph {
    graph: Graph,
    registry: Registry,
}

#[pymethods]
impl PyGraph {
    /// Loads `path` with `--set`-style overrides (`"node.param=value"`) and plugin libraries.
    #[staticmethod]
    #[pyo3(signature = (path, sets = Vec::new(), plugins = Vec::new()))]
    fn load(
        py: Python<'_>,
        path: PathBuf,
        sets: Vec<String>,
        plugins: Vec<PathBuf>,
    ) -> PyResult<PyGraph> {
        let mut registry = registry(&plugins)?;
        let mut diags = Diagnostics::default();
        let mut overrides = Vec::new();
        for set in &sets {
            match Override::parse(set) {
                Ok(o) => overrides.push(o),
                Err(d) => diags.push(*d),
            }
        }
        if !diags.is_empty() {
            return Err(graph_error(py, &diags));
        }
        let loaded = py.detach(|| {
            ocellus_engine::load_graph_with_plugins(&mut registry, &path, &overrides, true)
        });
        match loaded {
            Ok(graph) => Ok(PyGraph { graph, registry }),
            Err(mut diags) => {
                diags.sort();
                Err(graph_error(py, &diags))
            }
        }
    }

    /// Node names, in the order the engine runs them.
    #[getter]
    fn nodes(&self) -> Vec<String> {
        self.graph.nodes.iter().map(|n| n.name.clone()).collect()
    }

    /// Output names, in declaration order.
    #[getter]
    fn outputs(&self) -> Vec<String> {
        self.graph.outputs.iter().map(|o| o.name.clone()).collect()
    }

    /// Runs the graph. Returns `(outputs, report)`: `outputs` a list of `(name, tagged)`, the
    /// report a dict. With `submit`, distributable list maps run as tasks through it (see
    /// `ocellus.ray`).
    #[pyo3(signature = (outputs = Vec::new(), threads = 0, cache_dir = None, submit = None,
                        items_per_task = 0, item_cache = None, progress = None))]
    #[allow(clippy::too_many_arguments)]
    fn run<'py>(
        &self,
        py: Python<'py>,
        outputs: Vec<String>,
        threads: usize,
        cache_dir: Option<PathBuf>,
        submit: Option<Py<PyAny>>,
        items_per_task: usize,
        item_cache: Option<PathBuf>,
        progress: Option<Py<PyAny>>,
    ) -> PyResult<(Bound<'py, PyList>, Bound<'py, PyDict>)> {
        let distribution = submit.map(|submit| Distribution {
            runner: Arc::new(PyRunner { submit }),
            items_per_task,
            item_cache,
            // No lock of our own around the callback: the interpreter lock is the only one, so
            // two maps reporting at once cannot deadlock.
            progress: progress.map(|callback| {
                Arc::new(move |node: &str, done: usize, total: usize| {
                    Python::attach(|py| {
                        let _ = callback.call1(py, (node, done, total));
                    });
                }) as ocellus_engine::distribute::ItemProgressFn
            }),
        });
        let options = RunOptions {
            threads,
            outputs,
            cache_dir,
            distribution,
            ..RunOptions::default()
        };
        let result = py.detach(|| ocellus_engine::run(&self.graph, &options));
        let report = match result {
            Ok(report) => report,
            Err(e) => return Err(PyValueError::new_err(e.to_string())),
        };
        if !report.failures.is_empty() {
            let text: Vec<String> = report.failures.iter().map(|f| f.to_string()).collect();
            let err = RunError::new_err(text.join("\n"));
            let list = PyList::empty(py);
            for f in &report.failures {
                let item = PyDict::new(py);
                item.set_item("node", &f.node)?;
                item.set_item("op", &f.op)?;
                item.set_item("location", &f.location)?;
                item.set_item("message", &f.message)?;
                list.append(item)?;
            }
            err.value(py).setattr("failures", list)?;
            return Err(err);
        }
        let out = PyList::empty(py);
        for (name, value) in &report.outputs {
            out.append((name, tagged(py, value)?))?;
        }
        Ok((out, report_dict(py, &report)?))
    }

    /// The operator ids this graph can use (built-ins and its plugins).
    fn op_ids(&self) -> Vec<String> {
        self.registry.ids().map(str::to_string).collect()
    }
}

/// The run report as a dict: per-node status and time, and the distributed stages with their
/// per-worker table.
fn report_dict<'py>(
    py: Python<'py>,
    report: &ocellus_engine::RunReport,
) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("elapsed_s", report.elapsed.as_secs_f64())?;
    d.set_item("peak_bytes", report.peak_bytes)?;
    d.set_item("summary", report.summary_line())?;
    d.set_item("warnings", report.warnings.clone())?;
    let nodes = PyList::empty(py);
    for n in &report.nodes {
        let item = PyDict::new(py);
        item.set_item("name", &n.name)?;
        item.set_item("op", &n.op)?;
        item.set_item("status", format!("{:?}", n.status).to_lowercase())?;
        item.set_item("elapsed_s", n.elapsed.as_secs_f64())?;
        item.set_item("output_bytes", n.output_bytes)?;
        nodes.append(item)?;
    }
    d.set_item("nodes", nodes)?;
    let stages = PyList::empty(py);
    for s in &report.distributed {
        let item = PyDict::new(py);
        item.set_item("node", &s.node)?;
        item.set_item("op", &s.op)?;
        item.set_item("items", s.items)?;
        item.set_item("reused", s.reused)?;
        item.set_item("tasks", s.tasks)?;
        item.set_item("failed_tasks", s.failed_tasks)?;
        item.set_item("elapsed_s", s.elapsed.as_secs_f64())?;
        item.set_item("bytes_sent", s.bytes_sent)?;
        item.set_item("bytes_received", s.bytes_received)?;
        let workers = PyDict::new(py);
        for (name, w) in &s.workers {
            let wd = PyDict::new(py);
            wd.set_item("tasks", w.tasks)?;
            wd.set_item("items", w.items)?;
            wd.set_item("busy_s", w.busy_seconds)?;
            workers.set_item(name, wd)?;
        }
        item.set_item("workers", workers)?;
        stages.append(item)?;
    }
    d.set_item("distributed", stages)?;
    Ok(d)
}

/// A [`TaskRunner`] calling a Python `submit(stage, payloads)` that yields
/// `(task, ok, data, worker, seconds)` as tasks finish.
struct PyRunner {
    submit: Py<PyAny>,
}

impl TaskRunner for PyRunner {
    fn run(
        &self,
        stage: &Stage,
        tasks: Vec<Vec<u8>>,
        done: &mut dyn FnMut(TaskDone) -> Result<(), String>,
    ) -> Result<(), String> {
        Python::attach(|py| -> Result<(), String> {
            let info = PyDict::new(py);
            let py_err = |e: PyErr| format!("distributed runner: {e}");
            info.set_item("node", &stage.node).map_err(py_err)?;
            info.set_item("op", &stage.op).map_err(py_err)?;
            info.set_item("items", stage.items).map_err(py_err)?;
            info.set_item("reused", stage.reused).map_err(py_err)?;
            let payloads = PyList::empty(py);
            for t in &tasks {
                payloads.append(PyBytes::new(py, t)).map_err(py_err)?;
            }
            drop(tasks);
            let results = self.submit.call1(py, (info, payloads)).map_err(py_err)?;
            for item in results.bind(py).try_iter().map_err(py_err)? {
                let item = item.map_err(py_err)?;
                let (task, ok, data, worker, seconds): (
                    usize,
                    bool,
                    Bound<'_, PyAny>,
                    String,
                    f64,
                ) = item.extract().map_err(py_err)?;
                let result = if ok {
                    let bytes: Vec<u8> = data.extract().map_err(py_err)?;
                    Ok(bytes)
                } else {
                    Err(data.str().map(|s| s.to_string()).map_err(py_err)?)
                };
                done(TaskDone {
                    task,
                    result,
                    worker,
                    seconds,
                })?;
            }
            Ok(())
        })
    }
}

/// Runs one distributed task payload (the worker side of `ocellus.ray`) with the built-in
/// operators on `threads` threads (a Ray task holds `num_cpus` cores, so 1 by default); raises
/// `TaskError` when the chunk fails.
#[pyfunction]
#[pyo3(signature = (payload, threads = 1))]
fn run_task<'py>(py: Python<'py>, payload: &[u8], threads: usize) -> PyResult<Bound<'py, PyBytes>> {
    static REGISTRY: std::sync::OnceLock<Result<Registry, String>> = std::sync::OnceLock::new();
    static POOLS: Mutex<Vec<(usize, Arc<rayon::ThreadPool>)>> = Mutex::new(Vec::new());
    let threads = threads.max(1);
    let pool = {
        let mut pools = POOLS
            .lock()
            .map_err(|_| PyException::new_err("worker thread pools are unusable"))?;
        match pools.iter().find(|(n, _)| *n == threads) {
            Some((_, pool)) => pool.clone(),
            None => {
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .thread_name(|i| format!("ocellus-task-{i}"))
                    .build()
                    .map_err(|e| PyException::new_err(format!("worker threads: {e}")))?;
                let pool = Arc::new(pool);
                pools.push((threads, pool.clone()));
                pool
            }
        }
    };
    let result = py.detach(|| {
        let registry =
            REGISTRY.get_or_init(|| ocellus_nodes::builtin_registry().map_err(|e| e.to_string()));
        match registry {
            Ok(r) => pool.install(|| ocellus_engine::distribute::run_worker_task(r, payload)),
            Err(e) => Err(e.clone()),
        }
    });
    match result {
        Ok(bytes) => Ok(PyBytes::new(py, &bytes)),
        Err(message) => Err(TaskError::new_err(message)),
    }
}

/// The operator reference as JSON text (what `ocellus ops --json` prints).
#[pyfunction]
#[pyo3(signature = (plugins = Vec::new()))]
fn ops_json(plugins: Vec<PathBuf>) -> PyResult<String> {
    let registry = registry(&plugins)?;
    serde_json::to_string(&ocellus_engine::reference::ops_json(&registry))
        .map_err(|e| PyException::new_err(e.to_string()))
}

/// The engine's version.
#[pyfunction]
fn version() -> &'static str {
    env!("CARGO_PKG_VERSION")
}

fn le_bytes<T: Copy, const N: usize>(values: &[T], to_le: impl Fn(T) -> [u8; N]) -> Vec<u8> {
    let mut out = Vec::with_capacity(values.len() * N);
    for v in values {
        out.extend_from_slice(&to_le(*v));
    }
    out
}

fn flat_f32<const N: usize>(rows: &[[f32; N]]) -> Vec<u8> {
    le_bytes(rows.as_flattened(), f32::to_le_bytes)
}

fn json_tuple<'py>(py: Python<'py>, value: &Value) -> PyResult<Bound<'py, PyAny>> {
    let text = ocellus_engine::emit::json_text(value)
        .ok_or_else(|| PyException::new_err(format!("{} has no JSON form", value.port_type())))?;
    Ok(PyTuple::new(
        py,
        [
            "json".into_pyobject(py)?.into_any(),
            text.into_pyobject(py)?.into_any(),
        ],
    )?
    .into_any())
}

/// The tagged tuple of a value (see the module docs).
fn tagged<'py>(py: Python<'py>, value: &Value) -> PyResult<Bound<'py, PyAny>> {
    use ocellus_engine::value::{Descriptors, PixelData};
    let bytes = |b: Vec<u8>| PyBytes::new(py, &b);
    let t = match value {
        Value::Image(image) => {
            let (data, dtype) = match image.data() {
                PixelData::U8(d) => (d.clone(), "u8"),
                PixelData::U16(d) => (le_bytes(d, u16::to_le_bytes), "u16"),
                PixelData::F32(d) => (le_bytes(d, f32::to_le_bytes), "f32"),
            };
            (
                "image",
                bytes(data),
                image.height(),
                image.width(),
                image.channels().count(),
                dtype,
            )
                .into_pyobject(py)?
                .into_any()
        }
        Value::Keypoints(k) => {
            let mut out = Vec::with_capacity(k.len() * 24);
            for p in k.iter() {
                for v in [p.x, p.y, p.size, p.angle, p.response] {
                    out.extend_from_slice(&v.to_le_bytes());
                }
                out.extend_from_slice(&p.octave.to_le_bytes());
            }
            ("keypoints", bytes(out)).into_pyobject(py)?.into_any()
        }
        Value::Matches(m) => {
            let mut out = Vec::with_capacity(m.len() * 12);
            for x in m.iter() {
                out.extend_from_slice(&x.query.to_le_bytes());
                out.extend_from_slice(&x.train.to_le_bytes());
                out.extend_from_slice(&x.distance.to_le_bytes());
            }
            ("matches", bytes(out)).into_pyobject(py)?.into_any()
        }
        Value::Descriptors(d) => match d.as_ref() {
            Descriptors::Float { dim, data } => (
                "descriptors",
                "float",
                bytes(le_bytes(data, f32::to_le_bytes)),
                data.len().checked_div(*dim).unwrap_or(0),
                *dim,
            )
                .into_pyobject(py)?
                .into_any(),
            Descriptors::Binary { bytes: width, data } => (
                "descriptors",
                "binary",
                bytes(data.clone()),
                data.len().checked_div(*width).unwrap_or(0),
                *width,
            )
                .into_pyobject(py)?
                .into_any(),
        },
        Value::Matrix(m) => (
            "matrix",
            bytes(le_bytes(&m.data, f64::to_le_bytes)),
            m.rows,
            m.cols,
        )
            .into_pyobject(py)?
            .into_any(),
        Value::Points2D(p) => (
            "points2d",
            bytes(le_bytes(p.as_flattened(), f64::to_le_bytes)),
            p.len(),
        )
            .into_pyobject(py)?
            .into_any(),
        Value::PointCloud(c) => (
            "point_cloud",
            bytes(flat_f32(&c.positions)),
            c.positions.len(),
            c.colors.as_ref().map(|v| bytes(v.as_flattened().to_vec())),
            c.normals.as_ref().map(|v| bytes(flat_f32(v))),
        )
            .into_pyobject(py)?
            .into_any(),
        Value::Mesh(m) => PyTuple::new(
            py,
            [
                "mesh".into_pyobject(py)?.into_any(),
                bytes(flat_f32(&m.positions)).into_any(),
                m.positions.len().into_pyobject(py)?.into_any(),
                bytes(le_bytes(m.triangles.as_flattened(), u32::to_le_bytes)).into_any(),
                m.triangles.len().into_pyobject(py)?.into_any(),
                m.normals
                    .as_ref()
                    .map(|v| bytes(flat_f32(v)))
                    .into_pyobject(py)?
                    .into_any(),
                m.uvs
                    .as_ref()
                    .map(|v| bytes(flat_f32(v)))
                    .into_pyobject(py)?
                    .into_any(),
                m.colors
                    .as_ref()
                    .map(|v| bytes(flat_f32(v)))
                    .into_pyobject(py)?
                    .into_any(),
                m.tangents
                    .as_ref()
                    .map(|v| bytes(flat_f32(v)))
                    .into_pyobject(py)?
                    .into_any(),
            ],
        )?
        .into_any(),
        Value::Reconstruction(r) => reconstruction(py, r)?,
        Value::List(list) => {
            let items = PyList::empty(py);
            for item in list.items.iter() {
                items.append(tagged(py, item)?)?;
            }
            ("list", items).into_pyobject(py)?.into_any()
        }
        other => json_tuple(py, other)?,
    };
    Ok(t)
}

/// `("reconstruction", cameras, images, points)`: `cameras` maps id → camera JSON text;
/// `images` is a list of `(id, camera_id, name, pose JSON text, points2d f64 bytes, point ids
/// as i64 bytes with -1 for none)`; `points` is `(ids u64 bytes, xyz f64 bytes, rgb u8 bytes,
/// error f64 bytes, tracks)` with `tracks` a list of `[(image_id, index)…]`.
fn reconstruction<'py>(
    py: Python<'py>,
    r: &ocellus_engine::value::Reconstruction,
) -> PyResult<Bound<'py, PyAny>> {
    let json = |v: Value| ocellus_engine::emit::json_text(&v).unwrap_or_default();
    let cameras = PyDict::new(py);
    for (id, camera) in &r.cameras {
        cameras.set_item(id, json(Value::Camera(Arc::new(camera.clone()))))?;
    }
    let images = PyList::empty(py);
    for image in &r.images {
        let xy: Vec<f64> = image.points2d.iter().flat_map(|(p, _)| *p).collect();
        let ids: Vec<i64> = image
            .points2d
            .iter()
            .map(|(_, id)| id.map_or(-1, |i| i64::try_from(i).unwrap_or(-1)))
            .collect();
        images.append((
            image.id,
            image.camera_id,
            &image.name,
            json(Value::Pose(image.camera_from_world)),
            PyBytes::new(py, &le_bytes(&xy, f64::to_le_bytes)),
            PyBytes::new(py, &le_bytes(&ids, i64::to_le_bytes)),
        ))?;
    }
    let ids: Vec<u64> = r.points.iter().map(|p| p.id).collect();
    let xyz: Vec<f64> = r.points.iter().flat_map(|p| p.position).collect();
    let rgb: Vec<u8> = r.points.iter().flat_map(|p| p.color).collect();
    let err: Vec<f64> = r.points.iter().map(|p| p.error_px).collect();
    let tracks = PyList::empty(py);
    for p in &r.points {
        tracks.append(p.track.clone())?;
    }
    let points = (
        PyBytes::new(py, &le_bytes(&ids, u64::to_le_bytes)),
        PyBytes::new(py, &le_bytes(&xyz, f64::to_le_bytes)),
        PyBytes::new(py, &rgb),
        PyBytes::new(py, &le_bytes(&err, f64::to_le_bytes)),
        tracks,
    );
    Ok(("reconstruction", cameras, images, points)
        .into_pyobject(py)?
        .into_any())
}

#[pymodule]
fn _ocellus(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyGraph>()?;
    m.add_function(wrap_pyfunction!(run_task, m)?)?;
    m.add_function(wrap_pyfunction!(ops_json, m)?)?;
    m.add_function(wrap_pyfunction!(version, m)?)?;
    m.add("GraphError", m.py().get_type::<GraphError>())?;
    m.add("RunError", m.py().get_type::<RunError>())?;
    m.add("TaskError", m.py().get_type::<TaskError>())?;
    Ok(())
}
