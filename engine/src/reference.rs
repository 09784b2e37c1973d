//! The operator reference as data: what `ocellus ops --json` prints and `ocellus.ops()` returns
//! in Python, built from a registry (ids, ports, params with types, defaults, ranges, units and
//! docs).

use serde_json::{Value as Json, json};

use crate::op::{OpInfo, PortSpec, Registry};
use crate::params::ParamSpec;

fn port_json(p: &PortSpec) -> Json {
    json!({ "name": p.name, "type": p.ty.to_string(), "doc": p.doc, "optional": p.optional })
}

fn param_json(p: &ParamSpec) -> Json {
    json!({
        "name": p.name,
        "type": p.ty.to_string(),
        "default": serde_json::to_value(&p.default).unwrap_or(Json::Null),
        "range": p.range_text(),
        "min": p.min,
        "min_exclusive": p.min_exclusive,
        "max": p.max,
        "unit": p.unit,
        "doc": p.doc,
    })
}

/// The JSON description of one operator.
pub fn op_json(info: &OpInfo) -> Json {
    json!({
        "id": info.id,
        "family": info.family(),
        "version": info.version,
        "summary": info.summary,
        "doc": info.doc,
        "origin": info.origin.to_string(),
        "side_effects": info.side_effects,
        "inputs": info.inputs.iter().map(port_json).collect::<Vec<_>>(),
        "outputs": info.outputs.iter().map(port_json).collect::<Vec<_>>(),
        "params": info.params.iter().map(param_json).collect::<Vec<_>>(),
    })
}

/// Every operator of `registry`, sorted by id.
pub fn ops_json(registry: &Registry) -> Json {
    Json::Array(registry.iter().map(|f| op_json(f.info())).collect())
}
