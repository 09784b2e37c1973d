//! Loading operator plugins: shared libraries built against the `ocellus-plugin` SDK, whose
//! operators register in the [`Registry`] like built-ins, with [`Origin::Plugin`].
//!
//! Only the versioned C ABI of [`ocellus_plugin::abi`] crosses the boundary — plain `#[repr(C)]`
//! data and `extern "C"` function pointers, never Rust trait objects or `std` types, whose layout
//! differs between compilers (bevy removed its dynamic plugins for that reason). The loader checks,
//! in this order and before calling anything but the descriptor function:
//!
//! 1. the exported symbol `ocellus_plugin_descriptor` exists;
//! 2. the descriptor's first field, the ABI version, equals [`ABI_VERSION`] — nothing else of the
//!    descriptor is read before this check, as its layout may differ;
//! 3. the build fingerprint (ABI version, pointer width, byte order) equals the host's;
//! 4. every operator descriptor is valid (`family.name` id, port types ABI v1 can carry, params);
//!
//! then calls the plugin's `init` with the host services and registers one [`OpFactory`] per
//! operator. Libraries are never unloaded: factories and operator instances (possibly held by
//! caches or other threads) point into them, and unloading Rust code with thread-local
//! destructors is unsound on several platforms. A loaded plugin is trusted code — it runs in the
//! process — so the checks protect against mistakes (a stale build, a wrong file), not malice.

#![allow(unsafe_code)] // the C ABI boundary: every unsafe block says why it is sound

use std::ffi::c_void;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use ocellus_plugin::abi::{
    self, ABI_VERSION, BUILD_FINGERPRINT, Buffer, HostServices, OutValue, ParamArg, Str, ValueView,
};
use rayon::prelude::*;

use crate::op::{
    OpError, OpFactory, OpInfo, Operator, Origin, Outputs, PortSpec, Registry, RegistryError,
    RunContext, valid_op_id,
};
use crate::params::{ParamMap, ParamSpec, ParamType, ParamValue};
use crate::types::PortType;
use crate::value::{Channels, Image, Match, Matrix, Metrics, PixelData, Value};

/// Longest string read from a descriptor (a guard against garbage, not a format limit).
const MAX_DESCRIPTOR_STRING: usize = 1 << 20;
/// Most entries of a descriptor array (operators, ports, params, choices).
const MAX_DESCRIPTOR_ITEMS: usize = 10_000;

/// Why a plugin could not be loaded. Every variant names the library file.
#[derive(Debug, thiserror::Error)]
pub enum PluginError {
    /// The file is not a loadable library.
    #[error("cannot load plugin {}: {message}", path.display())]
    Open {
        /// The file.
        path: PathBuf,
        /// The loader's message.
        message: String,
    },
    /// The library does not export the descriptor function.
    #[error("{} is not an Ocellus plugin: it does not export `{}`", path.display(), abi::DESCRIPTOR_SYMBOL)]
    MissingSymbol {
        /// The file.
        path: PathBuf,
    },
    /// The descriptor function returned null.
    #[error("plugin {} returned no descriptor", path.display())]
    NullDescriptor {
        /// The file.
        path: PathBuf,
    },
    /// Plugin and host speak different ABI versions.
    #[error(
        "plugin {} was built for plugin ABI version {found}, but this Ocellus speaks version {expected}; rebuild it against ocellus-plugin {}",
        path.display(), ocellus_plugin::SDK_VERSION
    )]
    AbiMismatch {
        /// The file.
        path: PathBuf,
        /// The plugin's version.
        found: u32,
        /// The host's version.
        expected: u32,
    },
    /// Same ABI version, but built for another pointer width or byte order.
    #[error("plugin {} has build fingerprint `{plugin}`, but this Ocellus has `{host}`", path.display())]
    Fingerprint {
        /// The file.
        path: PathBuf,
        /// The plugin's fingerprint.
        plugin: String,
        /// The host's fingerprint.
        host: String,
    },
    /// A descriptor is malformed (bad id, unknown port type, bad param).
    #[error("plugin {}: {message}", path.display())]
    Invalid {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// The plugin's `init` failed.
    #[error("plugin {} failed to initialise: {message}", path.display())]
    Init {
        /// The file.
        path: PathBuf,
        /// The plugin's message.
        message: String,
    },
    /// An operator id is taken or malformed.
    #[error("plugin {}: {source}", path.display())]
    Registry {
        /// The file.
        path: PathBuf,
        /// The registry's error.
        source: RegistryError,
    },
}

/// What a loaded plugin provides.
#[derive(Debug, Clone, PartialEq)]
pub struct PluginInfo {
    /// Its name.
    pub name: String,
    /// The library file (canonical when it could be resolved).
    pub path: PathBuf,
    /// The `ocellus-plugin` version it was built with.
    pub sdk_version: String,
    /// Its operator ids.
    pub ops: Vec<String>,
}

/// Loads the plugin at `path` and registers its operators. Loading the same file again is a
/// no-op that returns the same [`PluginInfo`].
pub fn load_plugin(path: &Path, registry: &mut Registry) -> Result<PluginInfo, PluginError> {
    let path = std::fs::canonicalize(path).unwrap_or_else(|_| path.to_path_buf());
    // SAFETY: loading a library runs its initialisers; a plugin is trusted code chosen by the
    // user (see the module docs).
    let library = unsafe { libloading::Library::new(&path) }.map_err(|e| PluginError::Open {
        path: path.clone(),
        message: e.to_string(),
    })?;
    // SAFETY: the symbol's type is the one every plugin of every ABI version exports.
    let describe = unsafe { library.get::<abi::DescriptorFn>(abi::DESCRIPTOR_SYMBOL.as_bytes()) }
        .map(|symbol| *symbol)
        .map_err(|_| PluginError::MissingSymbol { path: path.clone() })?;
    // SAFETY: calling the descriptor function is part of every ABI version's contract.
    let descriptor = unsafe { describe() };
    // SAFETY: the pointer comes from the library's descriptor function, and the library is kept
    // loaded (forgotten below) once registration succeeds.
    let info = unsafe { register(descriptor, path, registry) }?;
    // Never unloaded: see the module docs.
    std::mem::forget(library);
    Ok(info)
}

/// Checks a descriptor and registers its operators.
///
/// # Safety
/// `descriptor` is null or points to a descriptor whose first field is a `u32`, and if that is
/// [`ABI_VERSION`], to a valid v1 descriptor whose pointers stay valid for the process.
unsafe fn register(
    descriptor: *const abi::PluginDescriptor,
    path: PathBuf,
    registry: &mut Registry,
) -> Result<PluginInfo, PluginError> {
    let invalid = |message: String| PluginError::Invalid {
        path: path.clone(),
        message,
    };
    if descriptor.is_null() {
        return Err(PluginError::NullDescriptor { path });
    }
    // SAFETY: every ABI version starts its descriptor with the `u32` ABI version (the caller's
    // guarantee), which is all we read before knowing the layout of the rest.
    let found = unsafe { descriptor.cast::<u32>().read() };
    if found != ABI_VERSION {
        return Err(PluginError::AbiMismatch {
            path,
            found,
            expected: ABI_VERSION,
        });
    }
    // SAFETY: same ABI version, so by the caller's guarantee the descriptor has this layout and
    // stays valid.
    let descriptor = unsafe { &*descriptor };
    let fingerprint =
        read_str(descriptor.fingerprint, "the build fingerprint").map_err(&invalid)?;
    if fingerprint != BUILD_FINGERPRINT {
        return Err(PluginError::Fingerprint {
            path,
            plugin: fingerprint,
            host: BUILD_FINGERPRINT.to_string(),
        });
    }
    let name = read_str(descriptor.name, "the plugin name").map_err(&invalid)?;
    if name.is_empty() {
        return Err(invalid("the plugin has an empty name".into()));
    }
    let sdk_version = read_str(descriptor.sdk_version, "the SDK version").map_err(&invalid)?;
    let origin = Origin::Plugin {
        plugin: name.clone(),
        library: path.clone(),
    };
    let ops = read_array(descriptor.ops, descriptor.op_count, "operators").map_err(&invalid)?;
    let mut factories = Vec::with_capacity(ops.len());
    for op in ops {
        factories.push(PluginFactory::new(op, &name, &origin).map_err(&invalid)?);
    }

    let mut err = Buffer::NULL;
    // SAFETY: `init` is called with services that live for the process (a `static`) and an error
    // slot we own; the plugin catches its own panics.
    let status = unsafe { (descriptor.init)(&HOST_SERVICES, &mut err) };
    let message = take_message(err);
    if status != abi::STATUS_OK {
        return Err(PluginError::Init { path, message });
    }

    let mut updated = registry.clone();
    let mut ids = Vec::with_capacity(factories.len());
    for factory in factories {
        let id = factory.info.id.clone();
        let already = updated
            .get(&id)
            .is_some_and(|f| f.info().origin == factory.info.origin);
        if !already {
            updated
                .register_factory(Arc::new(factory))
                .map_err(|source| PluginError::Registry {
                    path: path.clone(),
                    source,
                })?;
        }
        ids.push(id);
    }
    *registry = updated;
    tracing::debug!(plugin = %name, path = %path.display(), ops = ids.len(), "plugin loaded");
    Ok(PluginInfo {
        name,
        path,
        sdk_version,
        ops: ids,
    })
}

/// Plugin files named by `OCELLUS_PLUGIN_PATH`-style text: entries separated by `:` (`;` on
/// Windows), each a library file or a folder whose `*.so`, `*.dylib` and `*.dll` files are all
/// taken (sorted by name). Empty entries are ignored.
pub fn plugin_path_files(list: &str) -> Result<Vec<PathBuf>, String> {
    let separator = if cfg!(windows) { ';' } else { ':' };
    let mut files = Vec::new();
    for entry in list.split(separator).filter(|e| !e.trim().is_empty()) {
        let path = PathBuf::from(entry);
        if path.is_dir() {
            let read = std::fs::read_dir(&path)
                .map_err(|e| format!("cannot read plugin folder {}: {e}", path.display()))?;
            let mut found: Vec<PathBuf> = read
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| {
                    p.is_file()
                        && p.extension()
                            .is_some_and(|x| x == "so" || x == "dylib" || x == "dll")
                })
                .collect();
            found.sort();
            files.extend(found);
        } else {
            files.push(path);
        }
    }
    Ok(files)
}

fn read_str(s: Str, what: &str) -> Result<String, String> {
    if s.len > MAX_DESCRIPTOR_STRING {
        return Err(format!("{what} is {} bytes long", s.len));
    }
    if s.len > 0 && s.ptr.is_null() {
        return Err(format!("{what} is a null pointer"));
    }
    // SAFETY: descriptor strings point into the plugin's static data, alive while it is loaded.
    unsafe { s.as_str() }
        .map(str::to_string)
        .map_err(|e| format!("{what} is not UTF-8: {e}"))
}

fn read_array<'a, T>(ptr: *const T, count: usize, what: &str) -> Result<&'a [T], String> {
    if count == 0 {
        return Ok(&[]);
    }
    if count > MAX_DESCRIPTOR_ITEMS {
        return Err(format!("{count} {what}: more than {MAX_DESCRIPTOR_ITEMS}"));
    }
    if ptr.is_null() || !ptr.is_aligned() {
        return Err(format!("the {what} array is a null or misaligned pointer"));
    }
    // SAFETY: descriptor arrays point into the plugin's data, alive while it is loaded, with
    // `count` entries (checked non-null and aligned above).
    Ok(unsafe { std::slice::from_raw_parts(ptr, count) })
}

fn port_specs(
    ptr: *const abi::PortDescriptor,
    count: usize,
    what: &str,
) -> Result<Vec<PortSpec>, String> {
    let mut specs: Vec<PortSpec> = Vec::new();
    for p in read_array(ptr, count, what)? {
        let name = read_str(p.name, "a port name")?;
        let ty_name = read_str(p.ty, "a port type")?;
        if abi::port_type_code(&ty_name).is_none() {
            let known: Vec<&str> = abi::PORT_TYPES.iter().map(|(n, _)| *n).collect();
            return Err(format!(
                "port `{name}` has type `{ty_name}`, which plugin ABI v{ABI_VERSION} cannot carry (supported: {})",
                known.join(", ")
            ));
        }
        let ty = PortType::parse(&ty_name)
            .ok_or_else(|| format!("port `{name}`: unknown type `{ty_name}`"))?;
        if name.is_empty() || specs.iter().any(|s| s.name == name) {
            return Err(format!("{what}: empty or repeated port name `{name}`"));
        }
        let mut spec = PortSpec::new(&name, ty, &read_str(p.doc, "a port doc")?);
        spec.optional = p.optional;
        specs.push(spec);
    }
    Ok(specs)
}

fn param_spec(p: &abi::ParamDescriptor) -> Result<ParamSpec, String> {
    let name = read_str(p.name, "a parameter name")?;
    let valid_name = name.chars().next().is_some_and(|c| c.is_ascii_lowercase())
        && name
            .chars()
            .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '_');
    if !valid_name {
        return Err(format!("parameter name `{name}` is not lower_snake_case"));
    }
    let text = |s: Str| read_str(s, &format!("parameter `{name}`"));
    let (ty, default) = match p.kind {
        abi::PARAM_BOOL => (ParamType::Bool, ParamValue::Bool(p.default.boolean)),
        abi::PARAM_INT => (ParamType::Int, ParamValue::Int(p.default.integer)),
        abi::PARAM_FLOAT => {
            if !p.default.float.is_finite() {
                return Err(format!("parameter `{name}` has a non-finite default"));
            }
            (ParamType::Float, ParamValue::Float(p.default.float))
        }
        abi::PARAM_STR => (ParamType::Str, ParamValue::Str(text(p.default.text)?)),
        abi::PARAM_PATH => (ParamType::Path, ParamValue::Str(text(p.default.text)?)),
        abi::PARAM_CHOICE => {
            let choices = read_array(p.choices, p.choice_count, "choices")?
                .iter()
                .map(|c| text(*c))
                .collect::<Result<Vec<_>, _>>()?;
            let default = text(p.default.text)?;
            if !choices.contains(&default) {
                return Err(format!(
                    "parameter `{name}`: default `{default}` is not a choice"
                ));
            }
            (ParamType::Choice(choices), ParamValue::Str(default))
        }
        other => return Err(format!("parameter `{name}` has unknown kind {other}")),
    };
    if p.default.kind != p.kind {
        return Err(format!(
            "parameter `{name}`: the default's kind differs from the parameter's"
        ));
    }
    let spec = ParamSpec {
        name: name.clone(),
        ty,
        default,
        min: p.has_min.then_some(p.min),
        min_exclusive: false,
        max: p.has_max.then_some(p.max),
        unit: text(p.unit)?,
        doc: text(p.doc)?,
    };
    let default_number = match spec.default {
        ParamValue::Int(i) => Some(i as f64),
        ParamValue::Float(x) => Some(x),
        _ => None,
    };
    if let Some(x) = default_number {
        spec.check_range(x).map_err(|e| format!("default of {e}"))?;
    }
    Ok(spec)
}

/// One plugin operator: its description and entry points.
struct PluginFactory {
    info: OpInfo,
    plugin: Arc<str>,
    kinds: Vec<u32>,
    create: abi::CreateFn,
    run: abi::RunFn,
    destroy: abi::DestroyFn,
}

impl PluginFactory {
    fn new(op: &abi::OpDescriptor, plugin: &str, origin: &Origin) -> Result<PluginFactory, String> {
        let id = read_str(op.id, "an operator id")?;
        if !valid_op_id(&id) {
            return Err(format!(
                "operator id `{id}` is not of the form `family.name` (lower-case letters, digits, `_`)"
            ));
        }
        let context = |e: String| format!("operator `{id}`: {e}");
        let params_c = read_array(op.params, op.param_count, "parameters").map_err(context)?;
        let mut params: Vec<ParamSpec> = Vec::with_capacity(params_c.len());
        for p in params_c {
            let spec = param_spec(p).map_err(context)?;
            if params.iter().any(|q| q.name == spec.name) {
                return Err(context(format!(
                    "parameter `{}` is declared twice",
                    spec.name
                )));
            }
            params.push(spec);
        }
        let info = OpInfo {
            id: id.clone(),
            version: op.version,
            summary: read_str(op.summary, "a summary").map_err(context)?,
            doc: read_str(op.doc, "a doc")
                .map_err(context)?
                .trim()
                .to_string(),
            inputs: port_specs(op.inputs, op.input_count, "inputs").map_err(context)?,
            outputs: port_specs(op.outputs, op.output_count, "outputs").map_err(context)?,
            params,
            side_effects: op.side_effects,
            origin: origin.clone(),
        };
        Ok(PluginFactory {
            kinds: params_c.iter().map(|p| p.kind).collect(),
            info,
            plugin: plugin.into(),
            create: op.create,
            run: op.run,
            destroy: op.destroy,
        })
    }
}

fn param_value(kind: u32, value: &ParamValue) -> abi::ParamValue {
    let mut v = abi::ParamValue {
        kind,
        boolean: false,
        integer: 0,
        float: 0.0,
        text: Str::EMPTY,
    };
    match value {
        ParamValue::Bool(b) => v.boolean = *b,
        ParamValue::Int(i) => {
            v.integer = *i;
            v.float = *i as f64;
        }
        ParamValue::Float(x) => v.float = *x,
        ParamValue::Str(s) => v.text = Str::new(s),
        ParamValue::List(_) | ParamValue::None => {}
    }
    v
}

impl OpFactory for PluginFactory {
    fn info(&self) -> &OpInfo {
        &self.info
    }

    fn build(&self, params: &ParamMap) -> Result<Arc<dyn Operator>, String> {
        let mut args = Vec::with_capacity(self.info.params.len());
        for (spec, kind) in self.info.params.iter().zip(&self.kinds) {
            let value = params.get(&spec.name).unwrap_or(&spec.default);
            args.push(ParamArg {
                name: Str::new(&spec.name),
                value: param_value(*kind, value),
            });
        }
        let mut instance: *mut c_void = std::ptr::null_mut();
        let mut err = Buffer::NULL;
        // SAFETY: `args` (and the strings it borrows from `params` and `self`) outlive the call;
        // the out-pointers are ours; the plugin catches its own panics.
        let status = unsafe { (self.create)(args.as_ptr(), args.len(), &mut instance, &mut err) };
        let message = take_message(err);
        if status != abi::STATUS_OK {
            return Err(status_message(&self.plugin, status, &message));
        }
        if instance.is_null() {
            return Err(format!("plugin `{}` created a null instance", self.plugin));
        }
        Ok(Arc::new(PluginOperator {
            instance: Instance(instance),
            plugin: Arc::clone(&self.plugin),
            inputs: self.info.inputs.clone(),
            outputs: self.info.outputs.clone(),
            run: self.run,
            destroy: self.destroy,
        }))
    }
}

fn status_message(plugin: &str, status: u32, message: &str) -> String {
    match status {
        abi::STATUS_PANIC => format!("plugin `{plugin}` panicked: {message}"),
        abi::STATUS_ERROR => format!("plugin `{plugin}`: {message}"),
        other => format!("plugin `{plugin}` returned unknown status {other}: {message}"),
    }
}

/// An instance pointer owned by the plugin.
struct Instance(*mut c_void);

// SAFETY: the ABI requires instances to be usable from any thread, concurrently (the SDK's
// `PluginOp` is `Send + Sync`); the pointer is only passed back to the plugin.
unsafe impl Send for Instance {}
// SAFETY: as above.
unsafe impl Sync for Instance {}

struct PluginOperator {
    instance: Instance,
    plugin: Arc<str>,
    inputs: Vec<PortSpec>,
    outputs: Vec<PortSpec>,
    run: abi::RunFn,
    destroy: abi::DestroyFn,
}

impl Drop for PluginOperator {
    fn drop(&mut self) {
        // SAFETY: the instance came from this plugin's `create`, is destroyed once, here, and no
        // call can be running as we hold the last reference.
        unsafe { (self.destroy)(self.instance.0) };
    }
}

fn image_view(image: &Image) -> abi::ImageView {
    let (data, bytes) = match image.data() {
        PixelData::U8(v) => (v.as_ptr(), 1),
        PixelData::U16(v) => (v.as_ptr().cast::<u8>(), 2),
        PixelData::F32(v) => (v.as_ptr().cast::<u8>(), 4),
    };
    abi::ImageView {
        data,
        width: image.width(),
        height: image.height(),
        stride: image.row_stride(),
        format: abi::format_code(image.channels().count(), bytes).unwrap_or(0),
    }
}

impl Operator for PluginOperator {
    fn run(&self, ctx: &RunContext, inputs: &crate::op::Inputs<'_>) -> Result<Outputs, OpError> {
        let mut metric_names: Vec<Vec<abi::MetricView>> = Vec::new();
        // Matches are handed over as f64 rows; the converted arrays live until the call returns.
        let mut match_rows: Vec<Vec<f64>> = Vec::new();
        let mut views = Vec::with_capacity(self.inputs.len());
        for spec in &self.inputs {
            let mut view = ValueView::NONE;
            if let Some(value) = inputs.get(&spec.name) {
                match value {
                    Value::Image(image) => {
                        view.tag = abi::TYPE_IMAGE;
                        view.image = image_view(image);
                    }
                    Value::Matrix(m) => {
                        view.tag = abi::TYPE_MATRIX;
                        view.array = abi::ArrayView {
                            data: m.data.as_ptr(),
                            rows: m.rows,
                            cols: m.cols,
                        };
                    }
                    Value::Points2D(p) => {
                        view.tag = abi::TYPE_POINTS2D;
                        view.array = abi::ArrayView {
                            data: p.as_ptr().cast::<f64>(),
                            rows: p.len(),
                            cols: 2,
                        };
                    }
                    Value::Matches(m) => {
                        let flat: Vec<f64> = m
                            .iter()
                            .flat_map(|x| {
                                [
                                    f64::from(x.query),
                                    f64::from(x.train),
                                    f64::from(x.distance),
                                ]
                            })
                            .collect();
                        view.tag = abi::TYPE_MATCHES;
                        view.array = abi::ArrayView {
                            data: flat.as_ptr(),
                            rows: m.len(),
                            cols: 3,
                        };
                        // The heap buffer does not move when the vector does.
                        match_rows.push(flat);
                    }
                    Value::Scalar(x) => {
                        view.tag = abi::TYPE_SCALAR;
                        view.scalar = *x;
                    }
                    Value::Integer(i) if spec.ty == PortType::Scalar => {
                        view.tag = abi::TYPE_SCALAR;
                        view.scalar = *i as f64;
                    }
                    Value::Integer(i) => {
                        view.tag = abi::TYPE_INTEGER;
                        view.integer = *i;
                    }
                    Value::Bool(b) => {
                        view.tag = abi::TYPE_BOOL;
                        view.boolean = *b;
                    }
                    Value::Text(t) => {
                        view.tag = abi::TYPE_TEXT;
                        view.text = Str::new(t);
                    }
                    Value::Metrics(m) => {
                        let entries: Vec<abi::MetricView> = m
                            .iter()
                            .map(|(name, value)| abi::MetricView {
                                name: Str::new(name),
                                value: *value,
                            })
                            .collect();
                        view.tag = abi::TYPE_METRICS;
                        view.metrics = entries.as_ptr();
                        view.metric_count = entries.len();
                        // The heap buffer does not move when the vector does.
                        metric_names.push(entries);
                    }
                    other => {
                        return Err(OpError::input(
                            &spec.name,
                            format!("a {} cannot be passed to a plugin", other.port_type()),
                        ));
                    }
                }
            }
            views.push(view);
        }
        let context = abi::RunContext {
            node: Str::new(&ctx.node),
            threads: ctx.threads,
            element: ctx
                .element
                .and_then(|e| i64::try_from(e).ok())
                .unwrap_or(-1),
        };
        let mut outputs = vec![OutValue::NONE; self.outputs.len()];
        let mut err = Buffer::NULL;
        // SAFETY: every pointer in `views` and `context` borrows values that outlive the call
        // (`inputs`, `metric_names`, `match_rows`, `ctx`); `outputs` and `err` are ours; the instance is alive
        // (we hold it) and may be used concurrently; the plugin catches its own panics.
        let status = unsafe {
            (self.run)(
                self.instance.0,
                &context,
                views.as_ptr(),
                views.len(),
                outputs.as_mut_ptr(),
                outputs.len(),
                &mut err,
            )
        };
        drop(metric_names);
        drop(match_rows);
        let message = take_message(err);
        // Whatever the status, the host owns (and must free) what the plugin wrote.
        let mut converted = Vec::with_capacity(outputs.len());
        for (spec, out) in self.outputs.iter().zip(&outputs) {
            let value = if status == abi::STATUS_OK {
                Some(to_value(spec, out))
            } else {
                None
            };
            free_out(out);
            converted.push(value);
        }
        if status != abi::STATUS_OK {
            return Err(OpError::failed(status_message(
                &self.plugin,
                status,
                &message,
            )));
        }
        let mut result = Outputs::new();
        for (spec, value) in self.outputs.iter().zip(converted) {
            match value {
                Some(Ok(Some(v))) => result.set(&spec.name, v),
                Some(Ok(None)) | None => {}
                Some(Err(e)) => {
                    return Err(OpError::failed(format!(
                        "plugin `{}`: output `{}`: {e}",
                        self.plugin, spec.name
                    )));
                }
            }
        }
        Ok(result)
    }
}

/// Copies `len` values of `T` out of a host buffer written by a plugin.
fn read_buffer<T: Copy + Default>(b: &Buffer, len: usize) -> Result<Vec<T>, String> {
    let size = len
        .checked_mul(std::mem::size_of::<T>())
        .ok_or("buffer too large")?;
    if b.size != size {
        return Err(format!("buffer holds {} bytes, {size} expected", b.size));
    }
    let mut out = vec![T::default(); len];
    if size > 0 {
        if b.ptr.is_null() || b.ptr.align_offset(std::mem::align_of::<T>()) != 0 {
            return Err("null or misaligned buffer".into());
        }
        // SAFETY: the plugin wrote `size` bytes of `T` into this host allocation (checked size
        // and alignment above); `out` has room for exactly `size` bytes and does not overlap.
        unsafe {
            std::ptr::copy_nonoverlapping(b.ptr.cast_const(), out.as_mut_ptr().cast::<u8>(), size)
        };
    }
    Ok(out)
}

fn to_value(spec: &PortSpec, out: &OutValue) -> Result<Option<Value>, String> {
    let expected = abi::port_type_code(spec.ty.base_name());
    if out.tag == abi::TYPE_NONE {
        return Ok(None);
    }
    if Some(out.tag) != expected {
        return Err(format!(
            "type code {} does not match the declared {}",
            out.tag, spec.ty
        ));
    }
    let value = match out.tag {
        abi::TYPE_IMAGE => {
            let (channels, bytes) = abi::format_layout(out.format)
                .ok_or_else(|| format!("unknown pixel format {}", out.format))?;
            let channels = match channels {
                1 => Channels::Gray,
                3 => Channels::Rgb,
                _ => Channels::Rgba,
            };
            let n =
                Image::sample_count(out.width, out.height, channels).map_err(|e| e.to_string())?;
            let data = match bytes {
                1 => PixelData::U8(read_buffer(&out.buffer, n)?),
                2 => PixelData::U16(read_buffer(&out.buffer, n)?),
                _ => PixelData::F32(read_buffer(&out.buffer, n)?),
            };
            Value::image(
                Image::new(out.width, out.height, channels, data).map_err(|e| e.to_string())?,
            )
        }
        abi::TYPE_MATRIX => {
            let n = out.rows.checked_mul(out.cols).ok_or("matrix too large")?;
            let m = Matrix::new(out.rows, out.cols, read_buffer(&out.buffer, n)?)
                .map_err(|e| e.to_string())?;
            Value::Matrix(Arc::new(m))
        }
        abi::TYPE_POINTS2D => {
            let n = out.rows.checked_mul(2).ok_or("too many points")?;
            let flat: Vec<f64> = read_buffer(&out.buffer, n)?;
            Value::Points2D(Arc::new(
                flat.chunks_exact(2).map(|p| [p[0], p[1]]).collect(),
            ))
        }
        abi::TYPE_MATCHES => {
            let n = out.rows.checked_mul(3).ok_or("too many matches")?;
            let flat: Vec<f64> = read_buffer(&out.buffer, n)?;
            let index = |x: f64| -> Result<u32, String> {
                if x.fract() == 0.0 && (0.0..=f64::from(u32::MAX)).contains(&x) {
                    Ok(x as u32)
                } else {
                    Err(format!("match index {x} is not a whole number below 2^32"))
                }
            };
            let matches = flat
                .chunks_exact(3)
                .map(|r| {
                    Ok(Match {
                        query: index(r[0])?,
                        train: index(r[1])?,
                        distance: r[2] as f32,
                    })
                })
                .collect::<Result<Vec<_>, String>>()?;
            Value::Matches(Arc::new(matches))
        }
        abi::TYPE_SCALAR => Value::Scalar(out.scalar),
        abi::TYPE_INTEGER => Value::Integer(out.integer),
        abi::TYPE_BOOL => Value::Bool(out.boolean),
        abi::TYPE_TEXT => {
            let bytes: Vec<u8> = read_buffer(&out.buffer, out.buffer.size)?;
            Value::Text(String::from_utf8(bytes).map_err(|e| e.to_string())?.into())
        }
        abi::TYPE_METRICS => {
            let mut metrics = Metrics::new();
            for m in metric_entries(out)? {
                let bytes: Vec<u8> = read_buffer(&m.name, m.name.size)?;
                metrics.insert(
                    String::from_utf8(bytes).map_err(|e| e.to_string())?,
                    m.value,
                );
            }
            Value::metrics(metrics)
        }
        other => return Err(format!("unknown type code {other}")),
    };
    Ok(Some(value))
}

fn metric_entries(out: &OutValue) -> Result<Vec<abi::OutMetric>, String> {
    let entry = abi::OutMetric {
        name: Buffer::NULL,
        value: 0.0,
    };
    let size = out
        .rows
        .checked_mul(std::mem::size_of::<abi::OutMetric>())
        .ok_or("too many metrics")?;
    if out.buffer.size != size {
        return Err(format!(
            "metrics buffer holds {} bytes, {size} expected",
            out.buffer.size
        ));
    }
    let mut entries = vec![entry; out.rows];
    if size > 0 {
        if out.buffer.ptr.is_null()
            || out
                .buffer
                .ptr
                .align_offset(std::mem::align_of::<abi::OutMetric>())
                != 0
        {
            return Err("null or misaligned metrics buffer".into());
        }
        // SAFETY: the plugin wrote `rows` entries into this host allocation (size and alignment
        // checked above); `entries` has room for them and does not overlap.
        unsafe {
            std::ptr::copy_nonoverlapping(
                out.buffer.ptr.cast_const(),
                entries.as_mut_ptr().cast::<u8>(),
                size,
            );
        }
    }
    Ok(entries)
}

/// Frees every host buffer of an output value.
fn free_out(out: &OutValue) {
    if out.tag == abi::TYPE_METRICS
        && let Ok(entries) = metric_entries(out)
    {
        entries
            .iter()
            .for_each(|m| host_free(m.name.ptr, m.name.size, m.name.align));
    }
    host_free(out.buffer.ptr, out.buffer.size, out.buffer.align);
}

/// Reads and frees an error message written by a plugin.
fn take_message(err: Buffer) -> String {
    if err.ptr.is_null() {
        return "(no message)".to_string();
    }
    let text = read_buffer::<u8>(&err, err.size)
        .map(|b| String::from_utf8_lossy(&b).into_owned())
        .unwrap_or_else(|e| format!("(unreadable message: {e})"));
    host_free(err.ptr, err.size, err.align);
    text
}

/// The services every plugin receives; a `static`, so it outlives every plugin.
static HOST_SERVICES: HostServices = HostServices {
    abi_version: ABI_VERSION,
    log: host_log,
    thread_count: host_thread_count,
    parallel_for: host_parallel_for,
    alloc: host_alloc,
    free: host_free,
};

extern "C" fn host_log(level: u32, message: Str) {
    // SAFETY: the plugin lends the message for this call.
    let text = unsafe { message.as_str() }.unwrap_or("(invalid UTF-8 log message)");
    match level {
        abi::LOG_ERROR => tracing::error!(target: "ocellus::plugin", "{text}"),
        abi::LOG_WARN => tracing::warn!(target: "ocellus::plugin", "{text}"),
        abi::LOG_INFO => tracing::info!(target: "ocellus::plugin", "{text}"),
        _ => tracing::debug!(target: "ocellus::plugin", "{text}"),
    }
}

extern "C" fn host_thread_count() -> usize {
    rayon::current_num_threads()
}

/// A context pointer the plugin promises may be used from any thread.
#[derive(Clone, Copy)]
struct SharedContext(*const c_void);

// SAFETY: the ABI requires `parallel_for`'s context to be usable concurrently from any thread.
unsafe impl Send for SharedContext {}
// SAFETY: as above.
unsafe impl Sync for SharedContext {}

impl SharedContext {
    fn get(self) -> *const c_void {
        self.0
    }
}

extern "C" fn host_parallel_for(n: usize, ctx: *const c_void, body: abi::ParallelBody) {
    let ctx = SharedContext(ctx);
    // `body` must not unwind (the SDK catches panics in it); this runs on the pool of the
    // calling operator, the scheduler's rayon pool.
    (0..n).into_par_iter().for_each(|i| body(ctx.get(), i));
}

/// Bytes currently allocated through [`HostServices::alloc`] (a leak check for tests).
static LIVE_HOST_BYTES: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);

extern "C" fn host_alloc(size: usize, align: usize) -> *mut u8 {
    let Ok(layout) = std::alloc::Layout::from_size_align(size, align) else {
        return std::ptr::null_mut();
    };
    if size == 0 {
        // A dangling, aligned, non-null pointer, as for an empty `Vec`.
        return std::ptr::without_provenance_mut(align);
    }
    // SAFETY: `layout` has a non-zero size.
    let ptr = unsafe { std::alloc::alloc(layout) };
    if !ptr.is_null() {
        LIVE_HOST_BYTES.fetch_add(size, std::sync::atomic::Ordering::Relaxed);
    }
    ptr
}

extern "C" fn host_free(ptr: *mut u8, size: usize, align: usize) {
    if ptr.is_null() || size == 0 {
        return;
    }
    if let Ok(layout) = std::alloc::Layout::from_size_align(size, align) {
        // SAFETY: by the ABI, `ptr` came from `host_alloc(size, align)` and is freed once.
        unsafe { std::alloc::dealloc(ptr, layout) };
        LIVE_HOST_BYTES.fetch_sub(size, std::sync::atomic::Ordering::Relaxed);
    }
}

/// Reads fuzzer bytes as a sequence of choices; exhausted input reads as zeros.
struct FuzzBytes<'a> {
    data: &'a [u8],
}

impl<'a> FuzzBytes<'a> {
    fn byte(&mut self) -> u8 {
        match self.data.split_first() {
            Some((&b, rest)) => {
                self.data = rest;
                b
            }
            None => 0,
        }
    }

    fn take(&mut self, n: usize) -> &'a [u8] {
        let n = n.min(self.data.len());
        let (head, rest) = self.data.split_at(n);
        self.data = rest;
        head
    }

    fn u64(&mut self) -> u64 {
        let mut b = [0u8; 8];
        let src = self.take(8);
        b[..src.len()].copy_from_slice(src);
        u64::from_le_bytes(b)
    }

    /// Raw bytes as a descriptor string (possibly not UTF-8), or one of `known`.
    fn string(&mut self, known: &[&'static str]) -> Str {
        let choice = self.byte();
        let pick = usize::from(choice >> 2);
        if choice & 3 != 0 && !known.is_empty() {
            return Str::new(known[pick % known.len()]);
        }
        let bytes = self.take(pick);
        Str {
            ptr: if bytes.is_empty() && choice & 0x80 != 0 {
                std::ptr::null()
            } else {
                bytes.as_ptr()
            },
            len: bytes.len(),
        }
    }

    /// A count for an array, with the array's storage; a few choices give a huge count with a
    /// null pointer (which the reader must refuse without touching it).
    fn count(&mut self) -> (usize, bool) {
        let b = self.byte();
        match b {
            0xFF => (usize::MAX, true),
            0xFE => (MAX_DESCRIPTOR_ITEMS + 1, true),
            0xFD => (1, true),
            _ => (usize::from(b % 4), false),
        }
    }
}

unsafe extern "C" fn fuzz_init_ok(_: *const HostServices, _: *mut Buffer) -> u32 {
    abi::STATUS_OK
}

unsafe extern "C" fn fuzz_init_error(_: *const HostServices, _: *mut Buffer) -> u32 {
    abi::STATUS_ERROR
}

unsafe extern "C" fn fuzz_create(
    _: *const ParamArg,
    _: usize,
    _: *mut *mut c_void,
    _: *mut Buffer,
) -> u32 {
    abi::STATUS_ERROR
}

unsafe extern "C" fn fuzz_run(
    _: *const c_void,
    _: *const abi::RunContext,
    _: *const ValueView,
    _: usize,
    _: *mut OutValue,
    _: usize,
    _: *mut Buffer,
) -> u32 {
    abi::STATUS_ERROR
}

unsafe extern "C" fn fuzz_destroy(_: *mut c_void) {}

/// Builds a plugin descriptor from arbitrary bytes — ABI version, fingerprint, names, operator
/// ids, port names and types, parameter kinds, defaults, ranges and choices, array counts, null
/// pointers — and registers it as [`load_plugin`] would after finding the symbol. Every pointer
/// is valid for its count or null, so what is exercised is the descriptor *reader*: the checks a
/// stale or mistaken plugin meets. For the fuzz targets and their corpus replay test.
#[doc(hidden)]
pub fn register_descriptor_bytes(
    data: &[u8],
    registry: &mut Registry,
) -> Result<PluginInfo, PluginError> {
    let mut input = FuzzBytes { data };
    let header = input.byte();
    let abi_version = if header & 0x0F == 0x0F {
        u32::from(input.byte())
    } else {
        ABI_VERSION
    };
    let fingerprint = if header & 0x30 == 0x30 {
        input.string(&[])
    } else {
        Str::new(BUILD_FINGERPRINT)
    };
    let name = input.string(&["fuzzed", ""]);
    let sdk_version = input.string(&[ocellus_plugin::SDK_VERSION]);
    let type_names: Vec<&'static str> = abi::PORT_TYPES.iter().map(|(n, _)| *n).collect();

    // Storage the descriptor points into; built first, pointers taken after.
    let (op_count, op_null) = input.count();
    let real_ops = if op_null { 0 } else { op_count };
    let mut ports: Vec<(Vec<abi::PortDescriptor>, usize, bool)> = Vec::new();
    let mut params: Vec<(Vec<abi::ParamDescriptor>, usize, bool)> = Vec::new();
    let mut choices: Vec<Vec<Str>> = Vec::new();
    let mut op_fields = Vec::new();
    for _ in 0..real_ops {
        let id = input.string(&["fz.op", "fz.op2", "Bad", "fz."]);
        let version = u32::from(input.byte());
        let summary = input.string(&["summary"]);
        let doc = input.string(&["doc"]);
        let side_effects = input.byte() & 1 == 1;
        let mut port_lists = [0usize; 2];
        for slot in &mut port_lists {
            let (count, null) = input.count();
            let real = if null { 0 } else { count };
            let list = (0..real)
                .map(|_| abi::PortDescriptor {
                    name: input.string(&["a", "b", ""]),
                    ty: input.string(&type_names),
                    doc: input.string(&["port"]),
                    optional: input.byte() & 1 == 1,
                })
                .collect();
            ports.push((list, count, null));
            *slot = ports.len() - 1;
        }
        let (count, null) = input.count();
        let real = if null { 0 } else { count };
        let mut list = Vec::with_capacity(real);
        for _ in 0..real {
            let kind = u32::from(input.byte() % 8);
            let default_kind = if input.byte() & 7 == 7 {
                u32::from(input.byte() % 8)
            } else {
                kind
            };
            let default = abi::ParamValue {
                kind: default_kind,
                boolean: input.byte() & 1 == 1,
                integer: input.u64() as i64,
                float: f64::from_bits(input.u64()),
                text: input.string(&["x", "y", ""]),
            };
            let (choice_count, choice_null) = input.count();
            let real_choices = if choice_null { 0 } else { choice_count };
            choices.push(
                (0..real_choices)
                    .map(|_| input.string(&["x", "y", "z", ""]))
                    .collect(),
            );
            let flags = input.byte();
            list.push((
                abi::ParamDescriptor {
                    name: input.string(&["p", "q", "Bad", ""]),
                    kind,
                    default,
                    has_min: flags & 1 == 1,
                    min: f64::from_bits(input.u64()),
                    has_max: flags & 2 == 2,
                    max: f64::from_bits(input.u64()),
                    unit: input.string(&["px", ""]),
                    doc: input.string(&["param"]),
                    choices: std::ptr::null(),
                    choice_count,
                },
                choices.len() - 1,
                choice_null,
            ));
        }
        params.push((Vec::new(), count, null));
        let param_slot = params.len() - 1;
        op_fields.push((
            id,
            version,
            summary,
            doc,
            side_effects,
            port_lists,
            param_slot,
            list,
        ));
    }
    let init: abi::InitFn = if header & 0x40 != 0 {
        fuzz_init_error
    } else {
        fuzz_init_ok
    };

    // Now that no vector grows any more, point into them.
    let mut ops = Vec::with_capacity(op_fields.len());
    for (id, version, summary, doc, side_effects, port_lists, param_slot, list) in op_fields {
        let built: Vec<abi::ParamDescriptor> = list
            .into_iter()
            .map(|(mut p, choice_slot, null)| {
                if !null && p.choice_count > 0 {
                    p.choices = choices[choice_slot].as_ptr();
                }
                p
            })
            .collect();
        params[param_slot].0 = built;
        let pointer = |slot: usize| {
            let (list, count, null) = &ports[slot];
            let ptr = if *null || *count == 0 {
                std::ptr::null()
            } else {
                list.as_ptr()
            };
            (ptr, *count)
        };
        let (inputs, input_count) = pointer(port_lists[0]);
        let (outputs, output_count) = pointer(port_lists[1]);
        let (param_list, param_count, param_null) = &params[param_slot];
        ops.push(abi::OpDescriptor {
            id,
            version,
            summary,
            doc,
            inputs,
            input_count,
            outputs,
            output_count,
            params: if *param_null || *param_count == 0 {
                std::ptr::null()
            } else {
                param_list.as_ptr()
            },
            param_count: *param_count,
            side_effects,
            create: fuzz_create,
            run: fuzz_run,
            destroy: fuzz_destroy,
        });
    }
    let descriptor = abi::PluginDescriptor {
        abi_version,
        sdk_version,
        fingerprint,
        name,
        ops: if op_null || ops.is_empty() {
            std::ptr::null()
        } else {
            ops.as_ptr()
        },
        op_count,
        init,
    };
    // SAFETY: the descriptor is a v1 layout whose every pointer is null or points into `data`,
    // `ops`, `ports`, `params` or `choices` with exactly its count of entries, all alive until
    // this call returns; nothing registered keeps a pointer into them (names are copied), and the
    // registered operators' functions are the static ones above.
    unsafe { register(&descriptor, PathBuf::from("fuzz.so"), registry) }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)] // test code

    use std::sync::OnceLock;
    use std::sync::atomic::Ordering;

    use ocellus_plugin::export::{Built, OpEntry, descriptor};
    use ocellus_plugin::{
        Context, InputViews, OutputValue, OutputValues, OwnedSamples, Param, Params, PluginOp,
        Port, PortType as P,
    };

    use super::*;
    use crate::op::Inputs;

    /// Copies every input type ABI v1 carries to the outputs, through the SDK's safe API.
    struct Echo {
        offset: f64,
    }

    impl PluginOp for Echo {
        const ID: &'static str = "test.echo";
        const SUMMARY: &'static str = "Echoes its inputs.";
        const DOC: &'static str = "For the ABI tests.";
        const INPUTS: &'static [Port] = &[
            Port::new("image", P::Image, ""),
            Port::new("matrix", P::Matrix, ""),
            Port::new("points", P::Points2D, ""),
            Port::new("text", P::Text, ""),
            Port::new("metrics", P::Metrics, ""),
            Port::new("count", P::Integer, "").optional(),
            Port::new("flag", P::Bool, ""),
            Port::new("matches", P::Matches, ""),
        ];
        const OUTPUTS: &'static [Port] = &[
            Port::new("image", P::Image, ""),
            Port::new("matrix", P::Matrix, ""),
            Port::new("points", P::Points2D, ""),
            Port::new("text", P::Text, ""),
            Port::new("metrics", P::Metrics, ""),
            Port::new("count", P::Integer, ""),
            Port::new("flag", P::Bool, ""),
            Port::new("sum", P::Scalar, ""),
            Port::new("matches", P::Matches, ""),
        ];
        const PARAMS: &'static [Param] = &[Param::float("offset", 0.5, "").min(0.0).unit("px")];

        fn new(params: &Params) -> Result<Self, String> {
            Ok(Echo {
                offset: params.float("offset")?,
            })
        }

        fn run(&self, ctx: &Context, inputs: &InputViews) -> Result<OutputValues, String> {
            let image = inputs.image("image")?;
            let mut samples = Vec::new();
            for y in 0..image.height {
                samples.extend(image.row_u16(y).ok_or("not u16")?.iter().map(|v| v + 1));
            }
            let (rows, cols, data) = inputs.matrix("matrix")?;
            let points: Vec<[f64; 2]> = inputs
                .points2d("points")?
                .chunks_exact(2)
                .map(|p| [p[0] + self.offset, p[1]])
                .collect();
            let metrics = inputs
                .metrics("metrics")?
                .into_iter()
                .map(|(n, v)| (format!("{n}!"), v * 2.0))
                .collect();
            let count = if inputs.is_connected("count") {
                inputs.integer("count")?
            } else {
                -1
            };
            // Swap query and train, halve the distance.
            let matches = inputs
                .matches("matches")?
                .chunks_exact(3)
                .map(|m| (m[1] as u32, m[0] as u32, (m[2] / 2.0) as f32))
                .collect();
            let sum = std::sync::Mutex::new(0usize);
            ctx.parallel_for(10, |i| *sum.lock().unwrap() += i);
            let sum = *sum.lock().unwrap();
            Ok(OutputValues::new()
                .with(
                    "image",
                    OutputValue::Image {
                        width: image.width,
                        height: image.height,
                        channels: image.channels,
                        samples: OwnedSamples::U16(samples),
                    },
                )
                .with(
                    "matrix",
                    OutputValue::Matrix {
                        rows,
                        cols,
                        data: data.to_vec(),
                    },
                )
                .with("points", OutputValue::Points2D(points))
                .text("text", format!("{}|{}", inputs.text("text")?, ctx.node))
                .metrics("metrics", metrics)
                .integer("count", count)
                .bool("flag", !inputs.bool("flag")?)
                .scalar("sum", sum as f64)
                .with("matches", OutputValue::Matches(matches)))
        }
    }

    /// Panics while running.
    struct Boom;

    impl PluginOp for Boom {
        const ID: &'static str = "test.boom";
        const SUMMARY: &'static str = "Panics.";
        const DOC: &'static str = "For the ABI tests.";
        const INPUTS: &'static [Port] = &[];
        const OUTPUTS: &'static [Port] = &[Port::new("x", P::Scalar, "")];

        fn new(_: &Params) -> Result<Self, String> {
            Ok(Boom)
        }

        fn run(&self, ctx: &Context, _: &InputViews) -> Result<OutputValues, String> {
            ctx.parallel_for(4, |i| assert!(i != 2, "boom at {i}"));
            Ok(OutputValues::new())
        }
    }

    fn in_process() -> *const abi::PluginDescriptor {
        static BUILT: OnceLock<Built> = OnceLock::new();
        descriptor(&BUILT, "inproc", || {
            vec![OpEntry::of::<Echo>(), OpEntry::of::<Boom>()]
        })
    }

    fn register_copy(d: &abi::PluginDescriptor) -> Result<PluginInfo, PluginError> {
        let mut registry = Registry::new();
        // SAFETY: `d` is a v1 descriptor (or one whose first field is a u32) built from static
        // SDK data.
        unsafe { register(d, PathBuf::from("libfake.so"), &mut registry) }
    }

    #[test]
    fn values_cross_both_ways_and_host_buffers_are_freed() {
        let mut registry = Registry::new();
        // SAFETY: built by the SDK in this process, kept in a static.
        let info =
            unsafe { register(in_process(), PathBuf::from("inproc.so"), &mut registry) }.unwrap();
        assert_eq!(info.ops, ["test.echo", "test.boom"]);
        assert_eq!(info.sdk_version, ocellus_plugin::SDK_VERSION);
        let factory = registry.get("test.echo").unwrap();
        let op_info = factory.info().clone();
        assert_eq!(op_info.params[0].unit, "px");
        assert_eq!(op_info.params[0].min, Some(0.0));
        assert!(op_info.inputs[5].optional);
        assert!(matches!(op_info.origin, Origin::Plugin { ref plugin, .. } if plugin == "inproc"));

        let op = factory.build(&ParamMap::new()).unwrap();
        let image = Image::from_u16(2, 1, Channels::Rgb, vec![1, 2, 3, 4, 5, 6]).unwrap();
        let matrix = Matrix::new(2, 2, vec![1.0, 2.0, 3.0, 4.0]).unwrap();
        let metrics: Metrics = [("a".to_string(), 1.5)].into_iter().collect();
        let values = [
            Some(Value::image(image)),
            Some(Value::Matrix(Arc::new(matrix.clone()))),
            Some(Value::Points2D(Arc::new(vec![[1.0, 2.0], [3.0, 4.0]]))),
            Some(Value::Text("hi".into())),
            Some(Value::metrics(metrics)),
            None,
            Some(Value::Bool(true)),
            Some(Value::Matches(Arc::new(vec![
                Match {
                    query: 0,
                    train: 7,
                    distance: 3.0,
                },
                Match {
                    query: 4_000_000_000,
                    train: 1,
                    distance: 0.5,
                },
            ]))),
        ];
        let ctx = RunContext {
            node: "n1".into(),
            threads: 2,
            element: None,
        };
        let before = LIVE_HOST_BYTES.load(Ordering::SeqCst);
        let mut out = op
            .run(&ctx, &Inputs::new(&op_info.inputs, &values))
            .unwrap();
        assert_eq!(
            LIVE_HOST_BYTES.load(Ordering::SeqCst),
            before,
            "host buffers leaked"
        );
        let Some(Value::Image(img)) = out.take("image") else {
            panic!("image")
        };
        assert_eq!(img.as_u16().unwrap(), &[2, 3, 4, 5, 6, 7]);
        assert_eq!(out.take("matrix"), Some(Value::Matrix(Arc::new(matrix))));
        assert_eq!(
            out.take("points"),
            Some(Value::Points2D(Arc::new(vec![[1.5, 2.0], [3.5, 4.0]])))
        );
        assert_eq!(out.take("text"), Some(Value::Text("hi|n1".into())));
        assert_eq!(
            out.take("matches"),
            Some(Value::Matches(Arc::new(vec![
                Match {
                    query: 7,
                    train: 0,
                    distance: 1.5
                },
                Match {
                    query: 1,
                    train: 4_000_000_000,
                    distance: 0.25
                },
            ])))
        );
        let expected: Metrics = [("a!".to_string(), 3.0)].into_iter().collect();
        assert_eq!(out.take("metrics"), Some(Value::metrics(expected)));
        assert_eq!(out.take("count"), Some(Value::Integer(-1)));
        assert_eq!(out.take("flag"), Some(Value::Bool(false)));
        assert_eq!(out.take("sum"), Some(Value::Scalar(45.0)));

        // A panic inside the host's parallel_for comes back as an error naming the plugin.
        let boom = registry
            .get("test.boom")
            .unwrap()
            .build(&ParamMap::new())
            .unwrap();
        let err = boom
            .run(&ctx, &Inputs::new(&[], &[]))
            .unwrap_err()
            .to_string();
        assert!(err.contains("plugin `inproc` panicked: boom at 2"), "{err}");
        assert_eq!(
            LIVE_HOST_BYTES.load(Ordering::SeqCst),
            before,
            "error message leaked"
        );

        // Loading again is a no-op.
        // SAFETY: as above.
        unsafe { register(in_process(), PathBuf::from("inproc.so"), &mut registry) }.unwrap();
    }

    #[test]
    fn mismatches_are_refused_naming_both_sides() {
        // SAFETY: built by the SDK in this process.
        let good = unsafe { *in_process() };
        let mut abi2 = good;
        abi2.abi_version = 2;
        let err = register_copy(&abi2).unwrap_err().to_string();
        assert!(
            err.contains("libfake.so")
                && err.contains("version 2")
                && err.contains("speaks version 1"),
            "{err}"
        );

        let mut other = good;
        other.fingerprint = Str::new("ocellus-abi=1;ptr=16;endian=middle");
        let err = register_copy(&other).unwrap_err().to_string();
        assert!(
            err.contains("ptr=16;endian=middle") && err.contains(BUILD_FINGERPRINT),
            "{err}"
        );
    }

    #[test]
    fn unsupported_port_types_and_bad_ids_are_refused() {
        // SAFETY: built by the SDK in this process.
        let good = unsafe { *in_process() };
        // SAFETY: the SDK's descriptor holds two operators.
        let echo = unsafe { *good.ops };
        let mesh = [abi::PortDescriptor {
            name: Str::new("mesh"),
            ty: Str::new("Mesh"),
            doc: Str::EMPTY,
            optional: false,
        }];
        let mut op = echo;
        op.inputs = mesh.as_ptr();
        op.input_count = 1;
        let ops = [op];
        let mut d = good;
        d.ops = ops.as_ptr();
        d.op_count = 1;
        let err = register_copy(&d).unwrap_err().to_string();
        assert!(
            err.contains("`Mesh`") && err.contains("cannot carry") && err.contains("test.echo"),
            "{err}"
        );

        let mut op = echo;
        op.id = Str::new("NoFamily");
        let ops = [op];
        d.ops = ops.as_ptr();
        let err = register_copy(&d).unwrap_err().to_string();
        assert!(
            err.contains("`NoFamily`") && err.contains("family.name"),
            "{err}"
        );
    }

    #[test]
    fn plugin_path_lists_files_and_folders() {
        let dir = std::env::temp_dir().join(format!("ocellus-plugin-path-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        for f in ["b.so", "a.dylib", "c.dll", "notes.txt"] {
            std::fs::write(dir.join(f), "").unwrap();
        }
        let list = format!("{}::/x/liby.so", dir.display());
        let files = plugin_path_files(&list).unwrap();
        let names: Vec<String> = files
            .iter()
            .map(|f| f.file_name().unwrap().to_string_lossy().into_owned())
            .collect();
        assert_eq!(names, ["a.dylib", "b.so", "c.dll", "liby.so"]);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
