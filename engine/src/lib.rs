//! # ocellus-engine
//!
//! The engine of Ocellus: value and port types, RON graph loading with precise diagnostics,
//! validation, the demand-driven parallel scheduler, the result cache, output writers and the
//! snapshot helpers used by tests. It knows no operator: operators register through
//! [`op::Registry`].

pub mod op;
pub mod params;
pub mod types;
pub mod value;

pub use op::{
    Inputs, Op, OpError, OpFactory, OpInfo, Operator, Outputs, PortSpec, Registry, RunContext,
};
pub use params::{NoParams, ParamKind, ParamMap, ParamSpec, ParamType, ParamValue, Params};
pub use types::PortType;
pub use value::{Channels, Depth, Image, PixelData, PixelFormat, Value};
