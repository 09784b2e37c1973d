//! The C ABI, version [`ABI_VERSION`]: `#[repr(C)]` descriptors and value views shared by the host
//! (`ocellus-engine`) and plugins. Only plain data and `extern "C"` function pointers cross the
//! boundary — never Rust trait objects, `String`, `Vec` or other `std` types, whose layout is not
//! stable across compilers.
//!
//! # Ownership
//!
//! - Descriptors returned by [`DescriptorFn`] are owned by the plugin and live as long as the
//!   library stays loaded (the host never unloads a plugin).
//! - Inputs ([`ValueView`]), parameters ([`ParamArg`]) and the [`RunContext`] are **borrowed**
//!   for the duration of one `create`/`run` call; a plugin must not keep pointers into them.
//! - Outputs ([`OutValue`]) and error messages ([`Buffer`]) are allocated by the plugin through
//!   the host's [`HostServices::alloc`]; ownership passes to the host when the call returns,
//!   whatever the status. The host frees them with [`HostServices::free`] (same size and align).
//! - A plugin links its own `std`: its allocator, panic runtime, logging and thread pools are its
//!   own. It must never unwind into the host: every entry point catches panics and reports them as
//!   [`STATUS_PANIC`] (the [`export_plugin!`](crate::export_plugin) macro does this).

use std::ffi::c_void;

/// The ABI version. Bumped on any change of a `#[repr(C)]` type or of a rule in these docs. The
/// host reads this field first and refuses a mismatch without reading anything else.
pub const ABI_VERSION: u32 = 1;

/// Name of the symbol every plugin exports, of type [`DescriptorFn`].
pub const DESCRIPTOR_SYMBOL: &str = "ocellus_plugin_descriptor";

/// Things that must match between host and plugin for the ABI to work: ABI version, pointer width
/// and byte order. The compiler version is deliberately absent: a C ABI does not depend on it.
pub const BUILD_FINGERPRINT: &str = if cfg!(target_pointer_width = "64") {
    if cfg!(target_endian = "little") {
        "ocellus-abi=1;ptr=64;endian=little"
    } else {
        "ocellus-abi=1;ptr=64;endian=big"
    }
} else if cfg!(target_endian = "little") {
    "ocellus-abi=1;ptr=32;endian=little"
} else {
    "ocellus-abi=1;ptr=32;endian=big"
};

/// The type of the exported [`DESCRIPTOR_SYMBOL`]. Returns null if the plugin cannot describe
/// itself.
pub type DescriptorFn = unsafe extern "C" fn() -> *const PluginDescriptor;

/// Call succeeded.
pub const STATUS_OK: u32 = 0;
/// Call failed; the error buffer holds a UTF-8 message.
pub const STATUS_ERROR: u32 = 1;
/// The plugin panicked; the error buffer holds the panic message.
pub const STATUS_PANIC: u32 = 2;

/// A borrowed UTF-8 string (not NUL-terminated). `ptr` may be null only when `len` is 0.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub struct Str {
    /// First byte.
    pub ptr: *const u8,
    /// Length in bytes.
    pub len: usize,
}

impl Str {
    /// The empty string.
    pub const EMPTY: Str = Str {
        ptr: std::ptr::null(),
        len: 0,
    };

    /// Borrows `s`; the result is valid as long as `s` is.
    pub const fn new(s: &str) -> Str {
        Str {
            ptr: s.as_ptr(),
            len: s.len(),
        }
    }

    /// The text.
    ///
    /// # Safety
    /// `ptr..ptr+len` must be readable for `'a` (or `len` 0).
    pub unsafe fn as_str<'a>(self) -> Result<&'a str, std::str::Utf8Error> {
        if self.len == 0 || self.ptr.is_null() {
            return Ok("");
        }
        // SAFETY: the caller guarantees the range is readable for 'a.
        let bytes = unsafe { std::slice::from_raw_parts(self.ptr, self.len) };
        std::str::from_utf8(bytes)
    }
}

/// A buffer allocated with [`HostServices::alloc`]`(size, align)`, owned by whoever holds it;
/// `ptr` is null for "no buffer".
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub struct Buffer {
    /// Start (null: none).
    pub ptr: *mut u8,
    /// Bytes.
    pub size: usize,
    /// Alignment it was allocated with.
    pub align: usize,
}

impl Buffer {
    /// No buffer.
    pub const NULL: Buffer = Buffer {
        ptr: std::ptr::null_mut(),
        size: 0,
        align: 1,
    };
}

/// Log levels for [`HostServices::log`].
pub const LOG_ERROR: u32 = 1;
/// Warning.
pub const LOG_WARN: u32 = 2;
/// Information.
pub const LOG_INFO: u32 = 3;
/// Debugging.
pub const LOG_DEBUG: u32 = 4;

/// Services the host hands to [`PluginDescriptor::init`]; valid for the life of the process.
/// None of these functions unwinds.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub struct HostServices {
    /// Equal to [`ABI_VERSION`].
    pub abi_version: u32,
    /// Logs a UTF-8 message at a `LOG_*` level through the host's logger.
    pub log: extern "C" fn(level: u32, message: Str),
    /// Worker threads of the host pool the calling operator runs on.
    pub thread_count: extern "C" fn() -> usize,
    /// Calls `body(ctx, i)` for every `i` in `0..n` on the host's thread pool and returns when
    /// all calls have returned. `body` must not unwind and must be safe to call concurrently.
    pub parallel_for: extern "C" fn(n: usize, ctx: *const c_void, body: ParallelBody),
    /// Allocates `size` bytes aligned to `align` (a power of two); null on failure. `size` 0
    /// gives a dangling, aligned, non-null pointer.
    pub alloc: extern "C" fn(size: usize, align: usize) -> *mut u8,
    /// Frees a pointer from `alloc` with the same `size` and `align`. Null is ignored.
    pub free: extern "C" fn(ptr: *mut u8, size: usize, align: usize),
}

/// The body of [`HostServices::parallel_for`].
pub type ParallelBody = extern "C" fn(ctx: *const c_void, index: usize);

/// Port type codes of ABI v1 (tags of [`ValueView`] and [`OutValue`]); 0 means "no value".
pub const TYPE_NONE: u32 = 0;
/// `Image`.
pub const TYPE_IMAGE: u32 = 1;
/// `Matrix`.
pub const TYPE_MATRIX: u32 = 2;
/// `Points2D`.
pub const TYPE_POINTS2D: u32 = 3;
/// `Scalar`.
pub const TYPE_SCALAR: u32 = 4;
/// `Integer`.
pub const TYPE_INTEGER: u32 = 5;
/// `Bool`.
pub const TYPE_BOOL: u32 = 6;
/// `Text`.
pub const TYPE_TEXT: u32 = 7;
/// `Metrics`.
pub const TYPE_METRICS: u32 = 8;
/// `Matches`: `rows` correspondences as a `rows × 3` f64 array of (query index, train index,
/// distance); indices are whole numbers below 2³².
pub const TYPE_MATCHES: u32 = 9;

/// Port type names ABI v1 can carry, with their codes. A plugin port of any other type is
/// refused when the plugin is loaded.
pub const PORT_TYPES: [(&str, u32); 9] = [
    ("Image", TYPE_IMAGE),
    ("Matrix", TYPE_MATRIX),
    ("Points2D", TYPE_POINTS2D),
    ("Scalar", TYPE_SCALAR),
    ("Integer", TYPE_INTEGER),
    ("Bool", TYPE_BOOL),
    ("Text", TYPE_TEXT),
    ("Metrics", TYPE_METRICS),
    ("Matches", TYPE_MATCHES),
];

/// The code of a port type name, if ABI v1 carries it.
pub fn port_type_code(name: &str) -> Option<u32> {
    PORT_TYPES.iter().find(|(n, _)| *n == name).map(|(_, c)| *c)
}

/// Pixel format codes: `channels × depth`. Samples are interleaved, rows `stride` samples apart.
pub const FORMAT_GRAY_U8: u32 = 1;
/// Gray, 16-bit.
pub const FORMAT_GRAY_U16: u32 = 2;
/// Gray, 32-bit float.
pub const FORMAT_GRAY_F32: u32 = 3;
/// RGB, 8-bit.
pub const FORMAT_RGB_U8: u32 = 4;
/// RGB, 16-bit.
pub const FORMAT_RGB_U16: u32 = 5;
/// RGB, 32-bit float.
pub const FORMAT_RGB_F32: u32 = 6;
/// RGBA, 8-bit.
pub const FORMAT_RGBA_U8: u32 = 7;
/// RGBA, 16-bit.
pub const FORMAT_RGBA_U16: u32 = 8;
/// RGBA, 32-bit float.
pub const FORMAT_RGBA_F32: u32 = 9;

/// Channels (1, 3 or 4) and bytes per sample (1, 2 or 4) of a format code.
pub fn format_layout(format: u32) -> Option<(usize, usize)> {
    if !(FORMAT_GRAY_U8..=FORMAT_RGBA_F32).contains(&format) {
        return None;
    }
    let channels = [1, 3, 4][((format - 1) / 3) as usize];
    let bytes = [1, 2, 4][((format - 1) % 3) as usize];
    Some((channels, bytes))
}

/// The format code for channels (1, 3, 4) and bytes per sample (1, 2, 4).
pub fn format_code(channels: usize, bytes: usize) -> Option<u32> {
    let c = [1, 3, 4].iter().position(|&x| x == channels)?;
    let b = [1, 2, 4].iter().position(|&x| x == bytes)?;
    Some(1 + 3 * c as u32 + b as u32)
}

/// A borrowed image: `height` rows of `width × channels` samples, rows `stride` samples apart.
/// `data` is aligned for the sample type.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub struct ImageView {
    /// First sample (u8, u16 or f32 according to `format`).
    pub data: *const u8,
    /// Pixels per row.
    pub width: usize,
    /// Rows.
    pub height: usize,
    /// Samples from one row to the next (≥ `width × channels`).
    pub stride: usize,
    /// A `FORMAT_*` code.
    pub format: u32,
}

/// A borrowed row-major `rows × cols` array of f64 (a matrix; points are `n × 2`; matches are
/// `n × 3` rows of query index, train index, distance).
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub struct ArrayView {
    /// First entry.
    pub data: *const f64,
    /// Rows.
    pub rows: usize,
    /// Columns.
    pub cols: usize,
}

/// One named number of a `Metrics` value.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub struct MetricView {
    /// Name.
    pub name: Str,
    /// Value.
    pub value: f64,
}

/// A borrowed input value. `tag` (a `TYPE_*` code) says which field is meaningful; `TYPE_NONE`
/// is an unconnected optional input.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub struct ValueView {
    /// A `TYPE_*` code.
    pub tag: u32,
    /// `TYPE_IMAGE`.
    pub image: ImageView,
    /// `TYPE_MATRIX`, `TYPE_POINTS2D` (`cols` 2), `TYPE_MATCHES` (`cols` 3).
    pub array: ArrayView,
    /// `TYPE_TEXT`.
    pub text: Str,
    /// `TYPE_METRICS`: `metric_count` entries.
    pub metrics: *const MetricView,
    /// Entries of `metrics`.
    pub metric_count: usize,
    /// `TYPE_SCALAR`.
    pub scalar: f64,
    /// `TYPE_INTEGER`.
    pub integer: i64,
    /// `TYPE_BOOL`.
    pub boolean: bool,
}

impl ValueView {
    /// No value.
    pub const NONE: ValueView = ValueView {
        tag: TYPE_NONE,
        image: ImageView {
            data: std::ptr::null(),
            width: 0,
            height: 0,
            stride: 0,
            format: 0,
        },
        array: ArrayView {
            data: std::ptr::null(),
            rows: 0,
            cols: 0,
        },
        text: Str::EMPTY,
        metrics: std::ptr::null(),
        metric_count: 0,
        scalar: 0.0,
        integer: 0,
        boolean: false,
    };
}

/// One named number of an output `Metrics` value; `name` is a host-allocated UTF-8 buffer.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub struct OutMetric {
    /// Name bytes (align 1).
    pub name: Buffer,
    /// Value.
    pub value: f64,
}

/// An output value written by the plugin; every [`Buffer`] in it is allocated with the host's
/// `alloc` and owned by the host once `run` returns. The host presets `tag` to `TYPE_NONE`.
///
/// - image: `buffer` holds `height × width × channels` samples without padding, aligned to the
///   sample size; `width`, `height`, `format`.
/// - matrix: `rows × cols` f64 in `buffer`; points: `rows` points, `cols` 2; matches: `rows`
///   matches, `cols` 3.
/// - text: UTF-8 bytes in `buffer`.
/// - metrics: `rows` [`OutMetric`] entries in `buffer`.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub struct OutValue {
    /// A `TYPE_*` code.
    pub tag: u32,
    /// Image width.
    pub width: usize,
    /// Image height.
    pub height: usize,
    /// Image `FORMAT_*` code.
    pub format: u32,
    /// Array rows, metric count.
    pub rows: usize,
    /// Array columns.
    pub cols: usize,
    /// Payload.
    pub buffer: Buffer,
    /// `TYPE_SCALAR`.
    pub scalar: f64,
    /// `TYPE_INTEGER`.
    pub integer: i64,
    /// `TYPE_BOOL`.
    pub boolean: bool,
}

impl OutValue {
    /// Unset.
    pub const NONE: OutValue = OutValue {
        tag: TYPE_NONE,
        width: 0,
        height: 0,
        format: 0,
        rows: 0,
        cols: 0,
        buffer: Buffer::NULL,
        scalar: 0.0,
        integer: 0,
        boolean: false,
    };
}

/// Parameter kind codes.
pub const PARAM_BOOL: u32 = 1;
/// Integer (`i64`).
pub const PARAM_INT: u32 = 2;
/// Real number (`f64`).
pub const PARAM_FLOAT: u32 = 3;
/// String.
pub const PARAM_STR: u32 = 4;
/// One of `choices` (passed as a string).
pub const PARAM_CHOICE: u32 = 5;
/// A file path (passed as a string; the host resolves relative paths against the graph file).
pub const PARAM_PATH: u32 = 6;

/// A parameter value; `kind` says which field is meaningful (choice and path use `text`).
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub struct ParamValue {
    /// A `PARAM_*` code.
    pub kind: u32,
    /// `PARAM_BOOL`.
    pub boolean: bool,
    /// `PARAM_INT`.
    pub integer: i64,
    /// `PARAM_FLOAT`.
    pub float: f64,
    /// `PARAM_STR`, `PARAM_CHOICE`, `PARAM_PATH`.
    pub text: Str,
}

/// A parameter's schema.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub struct ParamDescriptor {
    /// Field name in the graph file.
    pub name: Str,
    /// A `PARAM_*` code.
    pub kind: u32,
    /// Default (same kind).
    pub default: ParamValue,
    /// Whether `min` applies.
    pub has_min: bool,
    /// Inclusive lower bound (numbers).
    pub min: f64,
    /// Whether `max` applies.
    pub has_max: bool,
    /// Inclusive upper bound (numbers).
    pub max: f64,
    /// Unit (`px`, `deg`), empty if none.
    pub unit: Str,
    /// What it does.
    pub doc: Str,
    /// `PARAM_CHOICE`: allowed names.
    pub choices: *const Str,
    /// Entries of `choices`.
    pub choice_count: usize,
}

/// A checked parameter handed to `create`: every declared parameter, in declaration order.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub struct ParamArg {
    /// Name.
    pub name: Str,
    /// Value.
    pub value: ParamValue,
}

/// A port.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub struct PortDescriptor {
    /// Name.
    pub name: Str,
    /// Type name, one of [`PORT_TYPES`].
    pub ty: Str,
    /// What flows through it.
    pub doc: Str,
    /// Inputs only: may be left unconnected.
    pub optional: bool,
}

/// What a running operator may know about its call (borrowed for the call).
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub struct RunContext {
    /// The node's name.
    pub node: Str,
    /// Worker threads of the pool the call runs on.
    pub threads: usize,
    /// For a mapped node, the list element index; -1 otherwise.
    pub element: i64,
}

/// `create(params, param_count, out_instance, err) -> status`.
pub type CreateFn = unsafe extern "C" fn(
    params: *const ParamArg,
    param_count: usize,
    out_instance: *mut *mut c_void,
    err: *mut Buffer,
) -> u32;

/// `run(instance, ctx, inputs, input_count, outputs, output_count, err) -> status`: inputs and
/// outputs in declaration order. May be called concurrently on one instance.
pub type RunFn = unsafe extern "C" fn(
    instance: *const c_void,
    ctx: *const RunContext,
    inputs: *const ValueView,
    input_count: usize,
    outputs: *mut OutValue,
    output_count: usize,
    err: *mut Buffer,
) -> u32;

/// `destroy(instance)`: frees an instance from `create`.
pub type DestroyFn = unsafe extern "C" fn(instance: *mut c_void);

/// `init(host) -> status`: called once, before any `create`; `host` lives for the process.
pub type InitFn = unsafe extern "C" fn(host: *const HostServices, err: *mut Buffer) -> u32;

/// One operator.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub struct OpDescriptor {
    /// `family.name`.
    pub id: Str,
    /// Bumped whenever outputs change for the same inputs and params.
    pub version: u32,
    /// One line.
    pub summary: Str,
    /// Method, formula, references.
    pub doc: Str,
    /// Inputs.
    pub inputs: *const PortDescriptor,
    /// Entries of `inputs`.
    pub input_count: usize,
    /// Outputs.
    pub outputs: *const PortDescriptor,
    /// Entries of `outputs`.
    pub output_count: usize,
    /// Parameters.
    pub params: *const ParamDescriptor,
    /// Entries of `params`.
    pub param_count: usize,
    /// Effects outside the graph: never cached.
    pub side_effects: bool,
    /// Builds an instance.
    pub create: CreateFn,
    /// Runs an instance.
    pub run: RunFn,
    /// Frees an instance.
    pub destroy: DestroyFn,
}

/// What [`DESCRIPTOR_SYMBOL`] returns. `abi_version` is the first field and stays first in every
/// future version, so a host can always read it.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub struct PluginDescriptor {
    /// [`ABI_VERSION`] the plugin was built with.
    pub abi_version: u32,
    /// Version of `ocellus-plugin` the plugin was built with.
    pub sdk_version: Str,
    /// [`BUILD_FINGERPRINT`] of the plugin.
    pub fingerprint: Str,
    /// Plugin name.
    pub name: Str,
    /// Operators.
    pub ops: *const OpDescriptor,
    /// Entries of `ops`.
    pub op_count: usize,
    /// Called once with the host services, before anything else but reading this descriptor.
    pub init: InitFn,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn format_codes_round_trip() {
        for channels in [1, 3, 4] {
            for bytes in [1, 2, 4] {
                let code = format_code(channels, bytes).unwrap_or(0);
                assert_eq!(format_layout(code), Some((channels, bytes)));
            }
        }
        assert_eq!(format_code(2, 1), None);
        assert_eq!(format_layout(0), None);
        assert_eq!(format_layout(10), None);
        assert_eq!(format_code(4, 4), Some(FORMAT_RGBA_F32));
    }

    #[test]
    fn fingerprint_names_what_must_match() {
        assert!(BUILD_FINGERPRINT.starts_with(&format!("ocellus-abi={ABI_VERSION};")));
        let width = format!("ptr={}", usize::BITS);
        assert!(BUILD_FINGERPRINT.contains(&width), "{BUILD_FINGERPRINT}");
        assert!(!BUILD_FINGERPRINT.contains("rustc"));
    }

    #[test]
    fn every_port_type_has_a_distinct_code() {
        let mut codes: Vec<u32> = PORT_TYPES.iter().map(|(_, c)| *c).collect();
        codes.sort_unstable();
        codes.dedup();
        assert_eq!(codes.len(), PORT_TYPES.len());
        assert!(!codes.contains(&TYPE_NONE));
        assert_eq!(port_type_code("Mesh"), None);
    }

    #[test]
    fn abi_version_is_the_first_field() {
        assert_eq!(std::mem::offset_of!(PluginDescriptor, abi_version), 0);
    }
}
