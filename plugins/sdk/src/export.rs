//! What [`export_plugin!`](crate::export_plugin) expands to: building the C descriptor from
//! [`PluginOp`] declarations, and the `extern "C"` trampolines. Not part of the public API.

use std::any::Any;
use std::ffi::c_void;
use std::panic::{AssertUnwindSafe, catch_unwind};
use std::sync::OnceLock;

use crate::abi::{self, Buffer, Str};
use crate::{Context, DefaultValue, InputViews, OutputValue, OwnedSamples, ParamKind};
use crate::{Params, PluginOp};

/// One operator's declarations and entry points.
pub struct OpEntry {
    id: &'static str,
    version: u32,
    summary: &'static str,
    doc: &'static str,
    inputs: &'static [crate::Port],
    outputs: &'static [crate::Port],
    params: &'static [crate::Param],
    side_effects: bool,
    create: abi::CreateFn,
    run: abi::RunFn,
    destroy: abi::DestroyFn,
}

impl OpEntry {
    /// The entry of `T`.
    pub fn of<T: PluginOp>() -> OpEntry {
        OpEntry {
            id: T::ID,
            version: T::VERSION,
            summary: T::SUMMARY,
            doc: T::DOC,
            inputs: T::INPUTS,
            outputs: T::OUTPUTS,
            params: T::PARAMS,
            side_effects: T::SIDE_EFFECTS,
            create: create::<T>,
            run: run::<T>,
            destroy: destroy::<T>,
        }
    }
}

/// The descriptor and the arrays it points into. Built once and kept in a `static`: the heap
/// buffers of the vectors never move, so the pointers stay valid for the life of the library.
pub struct Built {
    descriptor: abi::PluginDescriptor,
    _ops: Vec<abi::OpDescriptor>,
    _ports: Vec<Vec<abi::PortDescriptor>>,
    _params: Vec<Vec<abi::ParamDescriptor>>,
    _choices: Vec<Vec<Str>>,
}

// SAFETY: `Built` is immutable after construction and its raw pointers point into its own heap
// buffers or into `'static` data, so sharing it between threads is sound.
unsafe impl Sync for Built {}
// SAFETY: as above; nothing in it is tied to a thread.
unsafe impl Send for Built {}

fn port(p: &crate::Port) -> abi::PortDescriptor {
    abi::PortDescriptor {
        name: Str::new(p.name),
        ty: Str::new(p.ty.name()),
        doc: Str::new(p.doc),
        optional: p.optional,
    }
}

fn value(kind: u32, default: DefaultValue) -> abi::ParamValue {
    let mut v = abi::ParamValue {
        kind,
        boolean: false,
        integer: 0,
        float: 0.0,
        text: Str::EMPTY,
    };
    match default {
        DefaultValue::Bool(b) => v.boolean = b,
        DefaultValue::Int(i) => v.integer = i,
        DefaultValue::Float(x) => v.float = x,
        DefaultValue::Str(s) => v.text = Str::new(s),
    }
    v
}

impl Built {
    fn new(name: &'static str, entries: Vec<OpEntry>) -> Built {
        let mut ops = Vec::with_capacity(entries.len());
        let mut ports = Vec::new();
        let mut all_params = Vec::new();
        let mut all_choices = Vec::new();
        for e in &entries {
            let inputs: Vec<_> = e.inputs.iter().map(port).collect();
            let outputs: Vec<_> = e.outputs.iter().map(port).collect();
            let mut params = Vec::with_capacity(e.params.len());
            for p in e.params {
                let (kind, choices) = match p.kind {
                    ParamKind::Bool => (abi::PARAM_BOOL, Vec::new()),
                    ParamKind::Int => (abi::PARAM_INT, Vec::new()),
                    ParamKind::Float => (abi::PARAM_FLOAT, Vec::new()),
                    ParamKind::Str => (abi::PARAM_STR, Vec::new()),
                    ParamKind::Path => (abi::PARAM_PATH, Vec::new()),
                    ParamKind::Choice(c) => {
                        (abi::PARAM_CHOICE, c.iter().map(|s| Str::new(s)).collect())
                    }
                };
                params.push(abi::ParamDescriptor {
                    name: Str::new(p.name),
                    kind,
                    default: value(kind, p.default),
                    has_min: p.min.is_some(),
                    min: p.min.unwrap_or(0.0),
                    has_max: p.max.is_some(),
                    max: p.max.unwrap_or(0.0),
                    unit: Str::new(p.unit),
                    doc: Str::new(p.doc),
                    choices: choices.as_ptr(),
                    choice_count: choices.len(),
                });
                all_choices.push(choices);
            }
            ops.push(abi::OpDescriptor {
                id: Str::new(e.id),
                version: e.version,
                summary: Str::new(e.summary),
                doc: Str::new(e.doc),
                inputs: inputs.as_ptr(),
                input_count: inputs.len(),
                outputs: outputs.as_ptr(),
                output_count: outputs.len(),
                params: params.as_ptr(),
                param_count: params.len(),
                side_effects: e.side_effects,
                create: e.create,
                run: e.run,
                destroy: e.destroy,
            });
            ports.push(inputs);
            ports.push(outputs);
            all_params.push(params);
        }
        Built {
            descriptor: abi::PluginDescriptor {
                abi_version: abi::ABI_VERSION,
                sdk_version: Str::new(crate::SDK_VERSION),
                fingerprint: Str::new(abi::BUILD_FINGERPRINT),
                name: Str::new(name),
                ops: ops.as_ptr(),
                op_count: ops.len(),
                init,
            },
            _ops: ops,
            _ports: ports,
            _params: all_params,
            _choices: all_choices,
        }
    }
}

/// The body of the exported descriptor function: builds the descriptor once; null if that
/// panics.
pub fn descriptor(
    cell: &'static OnceLock<Built>,
    name: &'static str,
    entries: impl FnOnce() -> Vec<OpEntry>,
) -> *const abi::PluginDescriptor {
    catch_unwind(AssertUnwindSafe(|| {
        std::ptr::from_ref(&cell.get_or_init(|| Built::new(name, entries())).descriptor)
    }))
    .unwrap_or(std::ptr::null())
}

fn panic_text(payload: &(dyn Any + Send)) -> String {
    if let Some(s) = payload.downcast_ref::<&str>() {
        (*s).to_string()
    } else if let Some(s) = payload.downcast_ref::<String>() {
        s.clone()
    } else {
        "unknown panic".to_string()
    }
}

/// Copies `bytes` into a host buffer; `None` without a host or when allocation fails.
fn host_buffer<T: Copy>(data: &[T]) -> Option<Buffer> {
    let host = crate::host()?;
    let size = std::mem::size_of_val(data);
    let align = std::mem::align_of::<T>();
    let ptr = (host.alloc)(size, align);
    if ptr.is_null() {
        return None;
    }
    if size > 0 {
        // SAFETY: `ptr` is a fresh host allocation of `size` bytes aligned for `T`, disjoint
        // from `data`, which holds exactly `size` bytes of plain `Copy` data.
        unsafe { std::ptr::copy_nonoverlapping(data.as_ptr().cast::<u8>(), ptr, size) };
    }
    Some(Buffer { ptr, size, align })
}

fn free_buffer(b: Buffer) {
    if let Some(host) = crate::host() {
        (host.free)(b.ptr, b.size, b.align);
    }
}

/// Writes `message` to `err` (if the host can allocate it) and returns `status`.
fn fail(err: *mut Buffer, status: u32, message: &str) -> u32 {
    if !err.is_null()
        && let Some(buffer) = host_buffer(message.as_bytes())
    {
        // SAFETY: `err` is the host's out-pointer for this call, valid for one write.
        unsafe { err.write(buffer) };
    }
    status
}

thread_local! {
    /// Whether this thread is inside an entry point, where panics are caught and reported.
    static IN_CALL: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

/// A plugin normally has its own `std`, so its own panic hook: the default one would print every
/// caught panic (and a backtrace hint) to stderr although the host reports it as a node error.
/// Panics inside entry points are only logged at debug level; others go to the previous hook.
fn install_panic_hook() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        let previous = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            if IN_CALL.with(std::cell::Cell::get) {
                crate::log::debug(&info.to_string());
            } else {
                previous(info);
            }
        }));
    });
}

/// Runs `f` marked as inside an entry point, catching panics.
fn caught<R>(f: impl FnOnce() -> R) -> std::thread::Result<R> {
    let outer = IN_CALL.with(|c| c.replace(true));
    let result = catch_unwind(AssertUnwindSafe(f));
    IN_CALL.with(|c| c.set(outer));
    result
}

/// Runs `body`, turning `Err` and panics into a status with a message in `err`.
fn guarded(err: *mut Buffer, body: impl FnOnce() -> Result<(), String>) -> u32 {
    match caught(body) {
        Ok(Ok(())) => abi::STATUS_OK,
        Ok(Err(message)) => fail(err, abi::STATUS_ERROR, &message),
        Err(payload) => fail(err, abi::STATUS_PANIC, &panic_text(payload.as_ref())),
    }
}

unsafe extern "C" fn init(host: *const abi::HostServices, err: *mut Buffer) -> u32 {
    guarded(err, || {
        // SAFETY: the host passes a pointer to services it keeps alive for the process, or null.
        let services = unsafe { host.as_ref() }.ok_or("null host services")?;
        if services.abi_version != abi::ABI_VERSION {
            return Err(format!(
                "host ABI version {} differs from the plugin's {}",
                services.abi_version,
                abi::ABI_VERSION
            ));
        }
        crate::set_host(host);
        install_panic_hook();
        Ok(())
    })
}

unsafe extern "C" fn create<T: PluginOp>(
    params: *const abi::ParamArg,
    param_count: usize,
    out_instance: *mut *mut c_void,
    err: *mut Buffer,
) -> u32 {
    guarded(err, || {
        let args = if param_count == 0 || params.is_null() {
            &[][..]
        } else {
            // SAFETY: the host lends `param_count` entries for the duration of this call.
            unsafe { std::slice::from_raw_parts(params, param_count) }
        };
        let op = T::new(&Params { args })?;
        let instance = Box::into_raw(Box::new(op)).cast::<c_void>();
        if out_instance.is_null() {
            // SAFETY: `instance` was just made by `Box::into_raw` and is not shared.
            drop(unsafe { Box::from_raw(instance.cast::<T>()) });
            return Err("null instance pointer".into());
        }
        // SAFETY: the host's out-pointer, valid for one write.
        unsafe { out_instance.write(instance) };
        Ok(())
    })
}

unsafe extern "C" fn destroy<T: PluginOp>(instance: *mut c_void) {
    if instance.is_null() {
        return;
    }
    // A panicking `Drop` must not unwind into the host: it is caught and dropped silently, as
    // nobody could handle it.
    let _ = caught(|| {
        // SAFETY: `instance` came from `create::<T>` (`Box::into_raw`) and the host destroys it
        // exactly once, after its last `run`.
        drop(unsafe { Box::from_raw(instance.cast::<T>()) });
    });
}

unsafe extern "C" fn run<T: PluginOp>(
    instance: *const c_void,
    ctx: *const abi::RunContext,
    inputs: *const abi::ValueView,
    input_count: usize,
    outputs: *mut abi::OutValue,
    output_count: usize,
    err: *mut Buffer,
) -> u32 {
    guarded(err, || {
        // SAFETY: `instance` came from `create::<T>` and lives until `destroy`; `run` only
        // needs `&T`, and `T: Sync`.
        let op = unsafe { instance.cast::<T>().as_ref() }.ok_or("null instance")?;
        // SAFETY: borrowed from the host for this call.
        let ctx = unsafe { ctx.as_ref() }.ok_or("null context")?;
        let values = if input_count == 0 || inputs.is_null() {
            &[][..]
        } else {
            // SAFETY: the host lends `input_count` views for this call.
            unsafe { std::slice::from_raw_parts(inputs, input_count) }
        };
        if values.len() != T::INPUTS.len() || output_count != T::OUTPUTS.len() {
            return Err("the host passed a wrong number of ports".into());
        }
        let context = Context {
            // SAFETY: borrowed from the host for this call.
            node: unsafe { ctx.node.as_str() }.unwrap_or("?"),
            threads: ctx.threads,
            element: usize::try_from(ctx.element).ok(),
        };
        let views = InputViews {
            ports: T::INPUTS,
            values,
        };
        let mut produced = op.run(&context, &views)?;
        if let Some(extra) = produced
            .names()
            .find(|n| !T::OUTPUTS.iter().any(|p| p.name == *n))
        {
            return Err(format!("the operator set an undeclared output `{extra}`"));
        }
        if outputs.is_null() && output_count > 0 {
            return Err("null outputs".into());
        }
        // Convert everything first so that a failure leaks nothing into the host's slots.
        let mut converted = Vec::with_capacity(output_count);
        for port in T::OUTPUTS {
            let out = match produced.take(port.name) {
                Some(v) => to_out(port, v),
                None => Ok(abi::OutValue::NONE),
            };
            match out {
                Ok(o) => converted.push(o),
                Err(e) => {
                    converted.iter().for_each(free_out);
                    return Err(e);
                }
            }
        }
        for (i, out) in converted.into_iter().enumerate() {
            // SAFETY: the host lends `output_count` slots for this call; `i < output_count`.
            unsafe { outputs.add(i).write(out) };
        }
        Ok(())
    })
}

fn free_out(o: &abi::OutValue) {
    if o.tag == abi::TYPE_METRICS && !o.buffer.ptr.is_null() {
        // SAFETY: the buffer was filled by `to_out` with `rows` `OutMetric` entries.
        let entries = unsafe {
            std::slice::from_raw_parts(o.buffer.ptr.cast::<abi::OutMetric>().cast_const(), o.rows)
        };
        entries.iter().for_each(|m| free_buffer(m.name));
    }
    free_buffer(o.buffer);
}

fn no_memory(port: &crate::Port) -> String {
    format!(
        "output `{}`: the host could not allocate it (no host attached?)",
        port.name
    )
}

fn to_out(port: &crate::Port, value: OutputValue) -> Result<abi::OutValue, String> {
    let mut out = abi::OutValue::NONE;
    let mismatch = |got: &str| {
        format!(
            "output `{}` is declared {} but the operator produced {got}",
            port.name,
            port.ty.name()
        )
    };
    use crate::PortType as P;
    match (port.ty, value) {
        (
            P::Image,
            OutputValue::Image {
                width,
                height,
                channels,
                samples,
            },
        ) => {
            let (bytes, len) = match &samples {
                OwnedSamples::U8(v) => (1, v.len()),
                OwnedSamples::U16(v) => (2, v.len()),
                OwnedSamples::F32(v) => (4, v.len()),
            };
            let format = abi::format_code(channels, bytes).ok_or_else(|| {
                format!(
                    "output `{}`: {channels} channels is not 1, 3 or 4",
                    port.name
                )
            })?;
            let expected = width
                .checked_mul(height)
                .and_then(|n| n.checked_mul(channels));
            if expected != Some(len) {
                return Err(format!(
                    "output `{}`: {width}×{height}×{channels} needs {} samples, got {len}",
                    port.name,
                    expected.map_or("too many".to_string(), |n| n.to_string())
                ));
            }
            out.tag = abi::TYPE_IMAGE;
            out.width = width;
            out.height = height;
            out.format = format;
            out.buffer = match &samples {
                OwnedSamples::U8(v) => host_buffer(v),
                OwnedSamples::U16(v) => host_buffer(v),
                OwnedSamples::F32(v) => host_buffer(v),
            }
            .ok_or_else(|| no_memory(port))?;
        }
        (P::Matrix, OutputValue::Matrix { rows, cols, data }) => {
            if rows.checked_mul(cols) != Some(data.len()) {
                return Err(format!(
                    "output `{}`: a {rows}×{cols} matrix needs {} entries, got {}",
                    port.name,
                    rows.saturating_mul(cols),
                    data.len()
                ));
            }
            out.tag = abi::TYPE_MATRIX;
            out.rows = rows;
            out.cols = cols;
            out.buffer = host_buffer(&data).ok_or_else(|| no_memory(port))?;
        }
        (P::Points2D, OutputValue::Points2D(points)) => {
            out.tag = abi::TYPE_POINTS2D;
            out.rows = points.len();
            out.cols = 2;
            let flat: Vec<f64> = points.iter().flatten().copied().collect();
            out.buffer = host_buffer(&flat).ok_or_else(|| no_memory(port))?;
        }
        (P::Matches, OutputValue::Matches(matches)) => {
            out.tag = abi::TYPE_MATCHES;
            out.rows = matches.len();
            out.cols = 3;
            let flat: Vec<f64> = matches
                .iter()
                .flat_map(|&(q, t, d)| [f64::from(q), f64::from(t), f64::from(d)])
                .collect();
            out.buffer = host_buffer(&flat).ok_or_else(|| no_memory(port))?;
        }
        (P::Scalar, OutputValue::Scalar(x)) => {
            out.tag = abi::TYPE_SCALAR;
            out.scalar = x;
        }
        (P::Integer, OutputValue::Integer(i)) => {
            out.tag = abi::TYPE_INTEGER;
            out.integer = i;
        }
        (P::Bool, OutputValue::Bool(b)) => {
            out.tag = abi::TYPE_BOOL;
            out.boolean = b;
        }
        (P::Text, OutputValue::Text(t)) => {
            out.tag = abi::TYPE_TEXT;
            out.buffer = host_buffer(t.as_bytes()).ok_or_else(|| no_memory(port))?;
        }
        (P::Metrics, OutputValue::Metrics(entries)) => {
            let mut metrics = Vec::with_capacity(entries.len());
            for (name, value) in &entries {
                match host_buffer(name.as_bytes()) {
                    Some(b) => metrics.push(abi::OutMetric {
                        name: b,
                        value: *value,
                    }),
                    None => {
                        metrics
                            .iter()
                            .for_each(|m: &abi::OutMetric| free_buffer(m.name));
                        return Err(no_memory(port));
                    }
                }
            }
            out.tag = abi::TYPE_METRICS;
            out.rows = metrics.len();
            match host_buffer(&metrics) {
                Some(b) => out.buffer = b,
                None => {
                    metrics.iter().for_each(|m| free_buffer(m.name));
                    return Err(no_memory(port));
                }
            }
        }
        (_, other) => {
            let got = match other {
                OutputValue::Image { .. } => "an Image",
                OutputValue::Matrix { .. } => "a Matrix",
                OutputValue::Points2D(_) => "Points2D",
                OutputValue::Matches(_) => "Matches",
                OutputValue::Scalar(_) => "a Scalar",
                OutputValue::Integer(_) => "an Integer",
                OutputValue::Bool(_) => "a Bool",
                OutputValue::Text(_) => "Text",
                OutputValue::Metrics(_) => "Metrics",
            };
            return Err(mismatch(got));
        }
    }
    Ok(out)
}

/// State shared by the calls of one [`crate::Context::parallel_for`].
struct ParallelState<'a, F> {
    body: &'a F,
    panic: std::sync::Mutex<Option<Box<dyn Any + Send>>>,
}

extern "C" fn parallel_body<F: Fn(usize) + Sync>(ctx: *const c_void, index: usize) {
    // SAFETY: `ctx` is the `ParallelState<F>` that `parallel_for` passed to the host, alive until
    // the host's `parallel_for` returns, which is after this call returns.
    let Some(state) = (unsafe { ctx.cast::<ParallelState<'_, F>>().as_ref() }) else {
        return;
    };
    if let Err(payload) = caught(|| (state.body)(index))
        && let Ok(mut slot) = state.panic.lock()
    {
        slot.get_or_insert(payload);
    }
}

pub(crate) fn parallel_for<F: Fn(usize) + Sync>(host: &abi::HostServices, n: usize, body: &F) {
    let state = ParallelState {
        body,
        panic: std::sync::Mutex::new(None),
    };
    (host.parallel_for)(
        n,
        std::ptr::from_ref(&state).cast::<c_void>(),
        parallel_body::<F>,
    );
    let payload = state.panic.lock().ok().and_then(|mut p| p.take());
    if let Some(payload) = payload {
        // Re-raised inside the plugin, where the entry point's `catch_unwind` turns it into an
        // error status.
        std::panic::resume_unwind(payload);
    }
}
