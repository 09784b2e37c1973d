//! # ocellus-engine
//!
//! The engine of Ocellus: value and port types, RON graph loading with precise diagnostics,
//! validation, the demand-driven parallel scheduler, the result cache, output writers and the
//! snapshot helpers used by tests. It knows no operator: operators register through
//! [`op::Registry`].
//!
//! Layers, bottom up: [`ron_syntax`] (spanned RON) → [`spec`] (the file as written) →
//! [`resolve`] (validation into a [`graph::Graph`]) → [`exec`] (the scheduler, with [`cache`]) →
//! [`emit`] / [`summary`] / [`testing`] (outputs for users and tests).

pub mod buffer;
pub mod cache;
pub mod codec;
pub mod curves;
pub mod diag;
pub mod distribute;
pub mod emit;
pub mod exec;
mod exr_io;
pub mod graph;
pub mod image_io;
pub mod limits;
pub mod mesh_write;
pub mod op;
pub mod params;
pub mod plugin;
pub mod reference;
pub mod resolve;
pub mod ron_syntax;
pub mod sequence_write;
pub mod spec;
pub mod stream;
pub mod summary;
pub mod temp_files;
pub mod testing;
pub mod timeline;
pub mod types;
pub mod value;

pub use diag::{Diagnostic, Diagnostics};
pub use exec::{RunOptions, RunReport, run};
pub use graph::Graph;
pub use op::{
    Inputs, Op, OpError, OpFactory, OpInfo, Operator, Outputs, PortSpec, Registry, RunContext,
};
pub use params::{NoParams, ParamKind, ParamMap, ParamSpec, ParamType, ParamValue, Params};
pub use plugin::{PluginError, PluginInfo, load_plugin};
pub use resolve::{Override, load_graph, load_graph_with_plugins};
pub use types::PortType;
pub use value::{Channels, Depth, Image, PixelData, PixelFormat, Value};
