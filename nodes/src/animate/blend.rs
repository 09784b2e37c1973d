//! `animate.blend_shapes`: morph targets — a base mesh plus weighted offsets towards target
//! meshes with the same vertices (Lewis et al., "Practice and theory of blendshape facial
//! models", Eurographics STAR 2014).

use std::sync::Arc;

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Mesh, Value};

use super::skinning::apply_blend_shapes;
use crate::mesh::halfedge::{mesh_input, mesh_positions};
use crate::mesh::normals::{NormalWeighting, vertex_normals};

params! {
    /// Parameters of `animate.blend_shapes`.
    pub struct BlendShapesParams {
        /// One weight per target (0 keeps the base, 1 reaches the target; other values
        /// extrapolate). Missing weights are 0. Default empty.
        weights: Vec<f64> = Vec::new(),
    }
}

/// `animate.blend_shapes`. See the module documentation.
#[derive(Debug, Clone)]
pub struct BlendShapes {
    params: BlendShapesParams,
}

impl Op for BlendShapes {
    type Params = BlendShapesParams;
    const ID: &'static str = "animate.blend_shapes";
    const SUMMARY: &'static str =
        "Blends a base mesh towards target meshes by weights (morph targets).";
    const DOC: &'static str = r#"
Outputs `base + Σₖ weights[k] · (targets[k] − base)` per vertex: the delta (morph-target)
formulation of blend shapes (Lewis et al. 2014). Every target must have the base's vertex count;
triangles, uvs and colours are the base's. Normals are recomputed (area-weighted) when the base
has them. More weights than targets is an error; missing weights are 0. `weights` is a number
list, so an animation track can drive it (`tracks: { "blend.weights": (keys: [(0.0, [0, 0]),
(1.0, [1, 0.5])]) }`).

Example:
    "blend": (op: "animate.blend_shapes",
              inputs: { "base": "neutral.mesh", "targets": ["smile.mesh", "frown.mesh"] },
              params: (weights: [0.7, 0.0])),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new("base", PortType::Mesh, "The neutral mesh."),
            PortSpec::new(
                "targets",
                PortType::Mesh.list_of(),
                "Target shapes, each with the base's vertices.",
            ),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new("mesh", PortType::Mesh, "The blended mesh.")]
    }

    fn new(params: BlendShapesParams) -> Result<Self, String> {
        if !params.weights.iter().all(|w| w.is_finite()) {
            return Err("`weights` must be finite".into());
        }
        Ok(BlendShapes { params })
    }
}

impl Operator for BlendShapes {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let base = mesh_input(inputs, "base")?;
        let base_positions =
            mesh_positions(base).map_err(|e| OpError::input("base", e.to_string()))?;
        let Value::List(targets) = inputs.require("targets")? else {
            return Err(OpError::input("targets", "expected a list of meshes"));
        };
        if self.params.weights.len() > targets.items.len() {
            return Err(OpError::input(
                "targets",
                format!(
                    "{} weights for {} targets",
                    self.params.weights.len(),
                    targets.items.len()
                ),
            ));
        }
        let mut deltas = Vec::with_capacity(targets.items.len());
        for (k, t) in targets.items.iter().enumerate() {
            let Value::Mesh(t) = t else {
                return Err(OpError::input("targets", "expected a list of meshes"));
            };
            if t.positions.len() != base.positions.len() {
                return Err(OpError::input(
                    "targets",
                    format!(
                        "target {k} has {} vertices, the base {}",
                        t.positions.len(),
                        base.positions.len()
                    ),
                ));
            }
            let target = mesh_positions(t)
                .map_err(|e| OpError::input("targets", format!("target {k}: {e}")))?;
            deltas.push(
                target
                    .iter()
                    .zip(&base_positions)
                    .map(|(t, b)| [t[0] - b[0], t[1] - b[1], t[2] - b[2]])
                    .collect(),
            );
        }
        let mut weights = self.params.weights.clone();
        weights.resize(deltas.len(), 0.0);
        let positions = apply_blend_shapes(&base_positions, &deltas, &weights)
            .map_err(|e| OpError::failed(e.to_string()))?;
        let normals = base.normals.as_ref().map(|_| {
            let (n, _) = vertex_normals(&positions, &base.triangles, NormalWeighting::Area);
            n.iter().map(|v| v.map(|c| c as f32)).collect()
        });
        let out = Mesh {
            positions: positions.iter().map(|p| p.map(|c| c as f32)).collect(),
            normals,
            tangents: None,
            ..(**base).clone()
        };
        Ok(Outputs::new().with("mesh", Value::Mesh(Arc::new(out))))
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]

    use ocellus_engine::op::Op;

    use super::*;

    fn mesh(positions: Vec<[f32; 3]>) -> Mesh {
        Mesh {
            positions,
            triangles: vec![[0, 1, 2]],
            normals: None,
            uvs: None,
            colors: None,
            tangents: None,
        }
    }

    fn blend(weights: Vec<f64>, targets: Vec<Mesh>) -> Result<Mesh, OpError> {
        let base = mesh(vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]);
        let op = BlendShapes::new(BlendShapesParams { weights }).unwrap();
        let specs = BlendShapes::inputs();
        let values = [
            Some(Value::Mesh(Arc::new(base))),
            Some(Value::list(
                PortType::Mesh,
                targets
                    .into_iter()
                    .map(|m| Value::Mesh(Arc::new(m)))
                    .collect(),
            )),
        ];
        let mut out = op.run(
            &RunContext {
                node: "b".into(),
                threads: 1,
                element: None,
            },
            &Inputs::new(&specs, &values),
        )?;
        match out.take("mesh") {
            Some(Value::Mesh(m)) => Ok((*m).clone()),
            _ => panic!(),
        }
    }

    #[test]
    fn weights_blend_linearly_and_missing_weights_are_zero() {
        let up = mesh(vec![[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [0.0, 1.0, 1.0]]);
        let right = mesh(vec![[2.0, 0.0, 0.0], [3.0, 0.0, 0.0], [2.0, 1.0, 0.0]]);
        let m = blend(vec![0.5, 0.25], vec![up.clone(), right.clone()]).unwrap();
        assert_eq!(m.positions[0], [0.5, 0.0, 0.5]);
        assert_eq!(m.positions[2], [0.5, 1.0, 0.5]);
        let only_first = blend(vec![1.0], vec![up.clone(), right]).unwrap();
        assert_eq!(only_first.positions, up.positions);
        assert!(blend(vec![1.0, 1.0, 1.0], vec![up.clone()]).is_err());
        let short = mesh(vec![[0.0; 3]; 2]);
        assert!(blend(vec![1.0], vec![short]).is_err());
    }
}
