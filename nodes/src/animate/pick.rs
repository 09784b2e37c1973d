//! `animate.pick`: one mesh of a per-frame mesh list, by an index a timeline can drive
//! (`tracks: { "pick.index": "frame" }`).

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::Value;

use crate::capture::moving::resolve_index;

params! {
    /// Parameters of `animate.pick`.
    pub struct PickParams {
        /// Which element: 0 is the first; negative counts from the end (−1 is the last).
        /// Default 0.
        index: i64 = 0,
        /// Past the end, hold the last element instead of failing (a timeline longer than the
        /// simulation shows its final state). Default false.
        clamp: bool = false,
    }
}

/// `animate.pick`. See the module documentation.
#[derive(Debug, Clone)]
pub struct Pick {
    params: PickParams,
}

impl Op for Pick {
    type Params = PickParams;
    const ID: &'static str = "animate.pick";
    const SUMMARY: &'static str =
        "Picks one mesh of a mesh sequence by index (e.g. the current frame).";
    const DOC: &'static str = r#"
Outputs element `index` of the `frames` list (0 the first, negative from the end). An index
outside the list is an error naming the list's length, unless `clamp` is set: then indices past
either end give the first or last element. In an animated graph, drive the index with the frame
number: `animation: (frames: 48, tracks: { "pick.index": "frame" })`.

Example:
    "pick": (op: "animate.pick", inputs: { "frames": "cloth.frames" }, params: (index: 0)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "frames",
            PortType::Mesh.list_of(),
            "A mesh sequence.",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new("mesh", PortType::Mesh, "The selected mesh.")]
    }

    fn new(params: PickParams) -> Result<Self, String> {
        Ok(Pick { params })
    }
}

impl Operator for Pick {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let Value::List(list) = inputs.require("frames")? else {
            return Err(OpError::input("frames", "expected a list of meshes"));
        };
        let len = list.items.len();
        let index = match resolve_index(self.params.index, len) {
            Some(i) => i,
            None if self.params.clamp && len > 0 => {
                if self.params.index < 0 {
                    0
                } else {
                    len - 1
                }
            }
            None => {
                return Err(OpError::input(
                    "frames",
                    format!(
                        "index {} is outside a sequence of {len} meshes",
                        self.params.index
                    ),
                ));
            }
        };
        match list.items.get(index) {
            Some(mesh @ Value::Mesh(_)) => Ok(Outputs::new().with("mesh", mesh.clone())),
            _ => Err(OpError::input("frames", "expected a list of meshes")),
        }
    }
}
