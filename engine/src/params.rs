//! Typed operator parameters: schemas with defaults, ranges, units and docs, declared once per
//! operator with [`params!`](crate::params!) and checked when a graph is loaded.
//!
//! The graph loader validates user values against a [`ParamSpec`] list (unknown names, types,
//! ranges, choices — every problem with its source position), producing a complete [`ParamMap`]
//! with defaults filled in. The operator then receives its typed `Params` struct built from that
//! map, so a run never meets an unchecked value.

use std::collections::BTreeMap;
use std::fmt;
use std::path::PathBuf;

/// A checked parameter value in canonical form.
#[derive(Debug, Clone, PartialEq)]
pub enum ParamValue {
    /// A boolean.
    Bool(bool),
    /// An integer.
    Int(i64),
    /// A finite real number.
    Float(f64),
    /// A string, a choice name or a path.
    Str(String),
    /// A list.
    List(Vec<ParamValue>),
    /// An absent optional value.
    None,
}

impl fmt::Display for ParamValue {
    /// Canonical RON text: the same value always gives the same text (used in cache keys).
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            ParamValue::Bool(b) => write!(f, "{b}"),
            ParamValue::Int(i) => write!(f, "{i}"),
            ParamValue::Float(x) => {
                let text = format!("{x:?}");
                f.write_str(&text)
            }
            ParamValue::Str(s) => write!(f, "{s:?}"),
            ParamValue::List(items) => {
                f.write_str("[")?;
                for (i, item) in items.iter().enumerate() {
                    if i > 0 {
                        f.write_str(", ")?;
                    }
                    write!(f, "{item}")?;
                }
                f.write_str("]")
            }
            ParamValue::None => f.write_str("None"),
        }
    }
}

impl serde::Serialize for ParamValue {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        match self {
            ParamValue::Bool(b) => s.serialize_bool(*b),
            ParamValue::Int(i) => s.serialize_i64(*i),
            ParamValue::Float(x) => s.serialize_f64(*x),
            ParamValue::Str(t) => s.serialize_str(t),
            ParamValue::List(items) => items.serialize(s),
            ParamValue::None => s.serialize_none(),
        }
    }
}

/// The type of a parameter.
#[derive(Debug, Clone, PartialEq)]
pub enum ParamType {
    /// `true` / `false`.
    Bool,
    /// An integer.
    Int,
    /// A real number (integers are accepted and widened).
    Float,
    /// A string.
    Str,
    /// A file path: relative paths in a graph file resolve against the file's folder, relative
    /// paths given with `--set` against the working directory.
    Path,
    /// One of a fixed set of names, written as a string or a bare identifier.
    Choice(Vec<String>),
    /// A list, optionally of fixed length.
    List {
        /// Element type.
        element: Box<ParamType>,
        /// Required length, if fixed.
        len: Option<usize>,
    },
    /// An optional value: `None`, `Some(x)` or plain `x`.
    Optional(Box<ParamType>),
}

impl fmt::Display for ParamType {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            ParamType::Bool => f.write_str("bool"),
            ParamType::Int => f.write_str("int"),
            ParamType::Float => f.write_str("float"),
            ParamType::Str => f.write_str("string"),
            ParamType::Path => f.write_str("path"),
            ParamType::Choice(names) => {
                let quoted: Vec<String> = names.iter().map(|n| format!("\"{n}\"")).collect();
                write!(f, "one of {}", quoted.join(" | "))
            }
            ParamType::List { element, len } => match len {
                Some(n) => write!(f, "[{element}; {n}]"),
                None => write!(f, "[{element}]"),
            },
            ParamType::Optional(inner) => write!(f, "Option<{inner}>"),
        }
    }
}

/// A parameter's schema: name, type, default, allowed range, unit and documentation.
#[derive(Debug, Clone, PartialEq)]
pub struct ParamSpec {
    /// Field name in the graph file.
    pub name: String,
    /// Type.
    pub ty: ParamType,
    /// Default value (used when the graph omits the field).
    pub default: ParamValue,
    /// Smallest allowed value (numbers and number lists).
    pub min: Option<f64>,
    /// Whether `min` itself is excluded.
    pub min_exclusive: bool,
    /// Largest allowed value.
    pub max: Option<f64>,
    /// Unit, e.g. `px`, `deg`, `s`; empty when dimensionless.
    pub unit: String,
    /// What the parameter does.
    pub doc: String,
}

impl ParamSpec {
    /// A spec for a field of Rust type `T` with the given default.
    pub fn new<T: ParamKind>(name: &str, default: &T, doc: &str) -> ParamSpec {
        let (min, max) = T::natural_range();
        ParamSpec {
            name: name.to_string(),
            ty: T::param_type(),
            default: default.to_param(),
            min,
            min_exclusive: false,
            max,
            unit: String::new(),
            doc: doc.trim().to_string(),
        }
    }

    /// Sets an inclusive lower bound.
    pub fn min(mut self, value: impl Into<f64>) -> Self {
        self.min = Some(value.into());
        self.min_exclusive = false;
        self
    }

    /// Sets an exclusive lower bound.
    pub fn above(mut self, value: impl Into<f64>) -> Self {
        self.min = Some(value.into());
        self.min_exclusive = true;
        self
    }

    /// Sets an inclusive upper bound.
    pub fn max(mut self, value: impl Into<f64>) -> Self {
        self.max = Some(value.into());
        self
    }

    /// Sets the unit.
    pub fn unit(mut self, unit: &str) -> Self {
        self.unit = unit.to_string();
        self
    }

    /// Human-readable range, e.g. `0 ≤ x ≤ 255` or `x > 0`; `None` when unbounded.
    pub fn range_text(&self) -> Option<String> {
        let lo = self.min.map(|m| {
            let op = if self.min_exclusive { "<" } else { "≤" };
            format!("{} {op} ", fmt_bound(m))
        });
        let hi = self.max.map(|m| format!(" ≤ {}", fmt_bound(m)));
        match (lo, hi) {
            (None, None) => None,
            (lo, hi) => Some(format!(
                "{}x{}",
                lo.unwrap_or_default(),
                hi.unwrap_or_default()
            )),
        }
    }

    /// Checks a number against the range; the error says which bound fails.
    pub fn check_range(&self, x: f64) -> Result<(), String> {
        if let Some(min) = self.min {
            let bad = if self.min_exclusive {
                x <= min
            } else {
                x < min
            };
            if bad {
                let rel = if self.min_exclusive { ">" } else { "≥" };
                return Err(format!(
                    "`{}` must be {rel} {}, got {}",
                    self.name,
                    fmt_bound(min),
                    fmt_bound(x)
                ));
            }
        }
        if let Some(max) = self.max
            && x > max
        {
            return Err(format!(
                "`{}` must be ≤ {}, got {}",
                self.name,
                fmt_bound(max),
                fmt_bound(x)
            ));
        }
        Ok(())
    }
}

fn fmt_bound(x: f64) -> String {
    if x.fract() == 0.0 && x.abs() < 1e15 {
        format!("{}", x as i64)
    } else {
        format!("{x}")
    }
}

/// Checked parameters of one node, every field present (defaults filled in), ordered by name.
pub type ParamMap = BTreeMap<String, ParamValue>;

/// A Rust type usable as a parameter field.
pub trait ParamKind: Sized {
    /// The schema type.
    fn param_type() -> ParamType;
    /// Canonical value.
    fn to_param(&self) -> ParamValue;
    /// From a checked value; `None` if the value does not fit (a bug in the schema, reported as
    /// an error, never a panic).
    fn from_param(value: &ParamValue) -> Option<Self>;
    /// Bounds implied by the Rust type (e.g. 0 for unsigned).
    fn natural_range() -> (Option<f64>, Option<f64>) {
        (None, None)
    }
}

impl ParamKind for bool {
    fn param_type() -> ParamType {
        ParamType::Bool
    }
    fn to_param(&self) -> ParamValue {
        ParamValue::Bool(*self)
    }
    fn from_param(value: &ParamValue) -> Option<Self> {
        match value {
            ParamValue::Bool(b) => Some(*b),
            _ => None,
        }
    }
}

macro_rules! int_param_kind {
    ($($t:ty),*) => {$(
        impl ParamKind for $t {
            fn param_type() -> ParamType {
                ParamType::Int
            }
            fn to_param(&self) -> ParamValue {
                ParamValue::Int(i64::try_from(*self).unwrap_or(i64::MAX))
            }
            fn from_param(value: &ParamValue) -> Option<Self> {
                match value {
                    ParamValue::Int(i) => <$t>::try_from(*i).ok(),
                    _ => None,
                }
            }
            fn natural_range() -> (Option<f64>, Option<f64>) {
                (Some(<$t>::MIN as f64), Some(<$t>::MAX as f64))
            }
        }
    )*};
}
int_param_kind!(i32, i64, u8, u16, u32, u64, usize);

impl ParamKind for f64 {
    fn param_type() -> ParamType {
        ParamType::Float
    }
    fn to_param(&self) -> ParamValue {
        ParamValue::Float(*self)
    }
    fn from_param(value: &ParamValue) -> Option<Self> {
        match value {
            ParamValue::Float(x) => Some(*x),
            ParamValue::Int(i) => Some(*i as f64),
            _ => None,
        }
    }
}

impl ParamKind for f32 {
    fn param_type() -> ParamType {
        ParamType::Float
    }
    fn to_param(&self) -> ParamValue {
        ParamValue::Float(f64::from(*self))
    }
    fn from_param(value: &ParamValue) -> Option<Self> {
        f64::from_param(value).map(|x| x as f32)
    }
    fn natural_range() -> (Option<f64>, Option<f64>) {
        (Some(f64::from(f32::MIN)), Some(f64::from(f32::MAX)))
    }
}

impl ParamKind for String {
    fn param_type() -> ParamType {
        ParamType::Str
    }
    fn to_param(&self) -> ParamValue {
        ParamValue::Str(self.clone())
    }
    fn from_param(value: &ParamValue) -> Option<Self> {
        match value {
            ParamValue::Str(s) => Some(s.clone()),
            _ => None,
        }
    }
}

impl ParamKind for PathBuf {
    fn param_type() -> ParamType {
        ParamType::Path
    }
    fn to_param(&self) -> ParamValue {
        ParamValue::Str(self.to_string_lossy().into_owned())
    }
    fn from_param(value: &ParamValue) -> Option<Self> {
        match value {
            ParamValue::Str(s) => Some(PathBuf::from(s)),
            _ => None,
        }
    }
}

impl<T: ParamKind> ParamKind for Vec<T> {
    fn param_type() -> ParamType {
        ParamType::List {
            element: Box::new(T::param_type()),
            len: None,
        }
    }
    fn to_param(&self) -> ParamValue {
        ParamValue::List(self.iter().map(T::to_param).collect())
    }
    fn from_param(value: &ParamValue) -> Option<Self> {
        match value {
            ParamValue::List(items) => items.iter().map(T::from_param).collect(),
            _ => None,
        }
    }
    fn natural_range() -> (Option<f64>, Option<f64>) {
        T::natural_range()
    }
}

impl<T: ParamKind, const N: usize> ParamKind for [T; N] {
    fn param_type() -> ParamType {
        ParamType::List {
            element: Box::new(T::param_type()),
            len: Some(N),
        }
    }
    fn to_param(&self) -> ParamValue {
        ParamValue::List(self.iter().map(T::to_param).collect())
    }
    fn from_param(value: &ParamValue) -> Option<Self> {
        let items: Vec<T> = Vec::<T>::from_param(value)?;
        items.try_into().ok()
    }
    fn natural_range() -> (Option<f64>, Option<f64>) {
        T::natural_range()
    }
}

impl<T: ParamKind> ParamKind for Option<T> {
    fn param_type() -> ParamType {
        ParamType::Optional(Box::new(T::param_type()))
    }
    fn to_param(&self) -> ParamValue {
        match self {
            Some(v) => v.to_param(),
            None => ParamValue::None,
        }
    }
    fn from_param(value: &ParamValue) -> Option<Self> {
        match value {
            ParamValue::None => Some(None),
            other => T::from_param(other).map(Some),
        }
    }
    fn natural_range() -> (Option<f64>, Option<f64>) {
        T::natural_range()
    }
}

/// A typed parameter struct, generated by [`params!`](crate::params!).
pub trait Params: Sized + Clone + Default + Send + Sync + 'static {
    /// The schema of every field, in declaration order.
    fn schema() -> Vec<ParamSpec>;
    /// Builds the struct from a checked map.
    fn from_map(map: &ParamMap) -> Result<Self, String>;
    /// The canonical map of this struct's values.
    fn to_map(&self) -> ParamMap;
}

/// Operators without parameters.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct NoParams;

impl Params for NoParams {
    fn schema() -> Vec<ParamSpec> {
        Vec::new()
    }
    fn from_map(_: &ParamMap) -> Result<Self, String> {
        Ok(NoParams)
    }
    fn to_map(&self) -> ParamMap {
        ParamMap::new()
    }
}

/// Reads field `name` of type `T` from a checked map (used by [`params!`](crate::params!)).
pub fn take<T: ParamKind>(map: &ParamMap, name: &str) -> Result<T, String> {
    let value = map
        .get(name)
        .ok_or_else(|| format!("parameter `{name}` is missing after validation"))?;
    T::from_param(value).ok_or_else(|| {
        format!(
            "parameter `{name}` = {value} does not fit type {}",
            T::param_type()
        )
    })
}

/// Declares a typed parameter struct with its schema.
///
/// ```
/// ocellus_engine::params! {
///     /// Parameters of a blur.
///     pub struct BlurParams {
///         /// Standard deviation of the Gaussian.
///         sigma: f64 = 1.5 => [min = 0.0, max = 1000.0, unit = "px"],
///         /// Kernel size; 0 derives it from `sigma`.
///         ksize: u32 = 0,
///     }
/// }
/// use ocellus_engine::params::Params;
/// let schema = BlurParams::schema();
/// assert_eq!(schema[0].name, "sigma");
/// assert_eq!(schema[0].unit, "px");
/// assert_eq!(BlurParams::default().sigma, 1.5);
/// ```
///
/// Constraint keys after `=>` are methods of [`ParamSpec`]: `min`, `above` (exclusive minimum),
/// `max`, `unit`.
#[macro_export]
macro_rules! params {
    (
        $(#[$smeta:meta])*
        $vis:vis struct $name:ident {
            $(
                $(#[doc = $doc:literal])*
                $field:ident : $ty:ty = $default:expr $(=> [$($key:ident = $val:literal),* $(,)?])?
            ),* $(,)?
        }
    ) => {
        $(#[$smeta])*
        #[derive(Debug, Clone, PartialEq)]
        $vis struct $name {
            $(
                $(#[doc = $doc])*
                pub $field: $ty,
            )*
        }

        impl ::core::default::Default for $name {
            fn default() -> Self {
                Self { $($field: $default,)* }
            }
        }

        impl $crate::params::Params for $name {
            fn schema() -> ::std::vec::Vec<$crate::params::ParamSpec> {
                let defaults = <Self as ::core::default::Default>::default();
                ::std::vec![$(
                    $crate::params::ParamSpec::new::<$ty>(
                        stringify!($field),
                        &defaults.$field,
                        concat!($($doc, "\n"),*),
                    )$($(.$key($val))*)?
                ),*]
            }

            fn from_map(
                map: &$crate::params::ParamMap,
            ) -> ::core::result::Result<Self, ::std::string::String> {
                ::core::result::Result::Ok(Self {
                    $($field: $crate::params::take::<$ty>(map, stringify!($field))?,)*
                })
            }

            fn to_map(&self) -> $crate::params::ParamMap {
                let mut map = $crate::params::ParamMap::new();
                $(
                    map.insert(
                        stringify!($field).to_string(),
                        $crate::params::ParamKind::to_param(&self.$field),
                    );
                )*
                map
            }
        }
    };
}

/// Declares an enum parameter whose values are written as names (`"reflect_101"` or
/// `reflect_101`).
///
/// ```
/// ocellus_engine::param_enum! {
///     /// How to read pixels outside the image.
///     pub enum Border {
///         /// Repeat the edge pixel.
///         Clamp = "clamp",
///         /// Mirror without repeating the edge.
///         Reflect101 = "reflect_101",
///     }
/// }
/// use ocellus_engine::params::{ParamKind, ParamValue};
/// assert_eq!(Border::from_param(&ParamValue::Str("clamp".into())), Some(Border::Clamp));
/// assert_eq!(Border::Reflect101.name(), "reflect_101");
/// ```
#[macro_export]
macro_rules! param_enum {
    (
        $(#[$emeta:meta])*
        $vis:vis enum $name:ident {
            $(
                $(#[doc = $doc:literal])*
                $variant:ident = $text:literal
            ),+ $(,)?
        }
    ) => {
        $(#[$emeta])*
        #[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
        $vis enum $name {
            $(
                $(#[doc = $doc])*
                $variant,
            )+
        }

        impl $name {
            /// Every variant, in declaration order.
            #[allow(dead_code)]
            pub const ALL: &'static [$name] = &[$($name::$variant),+];

            /// The name used in graph files.
            pub fn name(self) -> &'static str {
                match self {
                    $($name::$variant => $text,)+
                }
            }
        }

        impl $crate::params::ParamKind for $name {
            fn param_type() -> $crate::params::ParamType {
                $crate::params::ParamType::Choice(::std::vec![$($text.to_string()),+])
            }
            fn to_param(&self) -> $crate::params::ParamValue {
                $crate::params::ParamValue::Str(self.name().to_string())
            }
            fn from_param(value: &$crate::params::ParamValue) -> ::core::option::Option<Self> {
                match value {
                    $crate::params::ParamValue::Str(s) => match s.as_str() {
                        $($text => ::core::option::Option::Some($name::$variant),)+
                        _ => ::core::option::Option::None,
                    },
                    _ => ::core::option::Option::None,
                }
            }
        }
    };
}

#[cfg(test)]
mod tests {
    use super::*;

    crate::param_enum! {
        /// Test enum.
        enum Mode {
            /// First.
            Fast = "fast",
            /// Second.
            Accurate = "accurate",
        }
    }

    crate::params! {
        /// Test params.
        struct TestParams {
            /// Sigma.
            sigma: f64 = 1.5 => [above = 0.0, max = 10.0, unit = "px"],
            /// Count.
            count: u32 = 3,
            /// Mode.
            mode: Mode = Mode::Fast,
            /// Weights.
            weights: [f32; 2] = [0.5, 0.5],
            /// Optional label.
            label: Option<String> = None,
        }
    }

    #[test]
    fn schema_reflects_declaration() {
        let schema = TestParams::schema();
        let names: Vec<&str> = schema.iter().map(|s| s.name.as_str()).collect();
        assert_eq!(names, ["sigma", "count", "mode", "weights", "label"]);
        assert_eq!(schema[0].default, ParamValue::Float(1.5));
        assert!(schema[0].min_exclusive);
        assert_eq!(schema[0].unit, "px");
        assert_eq!(schema[0].doc, "Sigma.");
        assert_eq!(schema[1].min, Some(0.0));
        assert_eq!(schema[1].max, Some(f64::from(u32::MAX)));
        assert_eq!(
            schema[2].ty,
            ParamType::Choice(vec!["fast".into(), "accurate".into()])
        );
        assert_eq!(schema[3].ty.to_string(), "[float; 2]");
        assert_eq!(schema[4].default, ParamValue::None);
    }

    #[test]
    fn map_round_trip() {
        let p = TestParams {
            sigma: 2.0,
            mode: Mode::Accurate,
            label: Some("x".into()),
            ..TestParams::default()
        };
        let back = TestParams::from_map(&p.to_map()).unwrap();
        assert_eq!(back, p);
    }

    #[test]
    fn take_reports_misfit_without_panicking() {
        let mut map = TestParams::default().to_map();
        map.insert("count".into(), ParamValue::Int(-1));
        assert!(TestParams::from_map(&map).is_err());
        map.remove("count");
        assert!(TestParams::from_map(&map).is_err());
    }

    #[test]
    fn range_checks() {
        let spec = &TestParams::schema()[0];
        assert!(spec.check_range(0.0).is_err());
        assert!(spec.check_range(1e-9).is_ok());
        assert!(spec.check_range(10.0).is_ok());
        assert!(spec.check_range(10.5).is_err());
        assert_eq!(spec.range_text().as_deref(), Some("0 < x ≤ 10"));
    }

    #[test]
    fn canonical_display() {
        let v = ParamValue::List(vec![
            ParamValue::Float(1.0),
            ParamValue::Int(2),
            ParamValue::Str("a\"b".into()),
            ParamValue::None,
        ]);
        assert_eq!(v.to_string(), r#"[1.0, 2, "a\"b", None]"#);
    }
}
