//! `sfm.pair_lists`: the image pairs of a collection as lists, one element per pair, so that
//! per-pair work (descriptor matching, patch matching) is an ordinary list map: it runs in
//! parallel locally and as distributed tasks with `--ray`, and each pair is cached on its own.
//!
//! Pairs are chosen as [`sfm.match_pairs`](super::pairs) chooses them (exhaustive, sequential
//! window, or retrieval by descriptor similarity), in the same order.

use ocellus_engine::value::{Descriptors, Matrix};
use ocellus_engine::{
    Inputs, Op, OpError, Operator, Outputs, PortSpec, PortType, RunContext, Value, params,
};

use super::pairs::{PairOptions, PairSelection, keypoint_lists, required_list, select_pairs};

params! {
    /// Parameters of `sfm.pair_lists`.
    pub struct PairListsParams {
        /// Which pairs: "exhaustive", "sequential" or "similarity".
        selection: PairSelection = PairSelection::Exhaustive,
        /// Sequential selection: each image is paired with the next `window` images.
        window: u32 = 5 => [min = 1],
        /// Similarity selection: similar images kept per image.
        neighbors: u32 = 10 => [min = 1],
        /// Similarity selection: strongest features per image used to rank similarity.
        retrieval_features: u32 = 256 => [min = 1],
        /// Similarity selection: Lowe's ratio test of the retrieval matching.
        ratio: f64 = 0.8 => [min = 0.0],
    }
}

/// `sfm.pair_lists`. See the [module documentation](self).
#[derive(Debug, Clone)]
pub struct PairLists {
    options: PairOptions,
}

impl Op for PairLists {
    type Params = PairListsParams;
    const ID: &'static str = "sfm.pair_lists";
    const SUMMARY: &'static str = "Selects image pairs and lists each pair's keypoints and descriptors, for per-pair list maps.";
    const DOC: &'static str = r#"
Pair selection as in `sfm.match_pairs` (Schönberger & Frahm, CVPR 2016, §4.1): `selection:
"exhaustive"` (every pair i < j), `"sequential"` (each image with the next `window`), or
`"similarity"` (each image with the `neighbors` images its `retrieval_features` strongest
features match most often under the `ratio` test).

Outputs one list element per pair, in the order of the rows of `pairs` (an N×2 matrix of image
indices `[i, j]`): `keypoints_a`/`descriptors_a` of image i and `keypoints_b`/`descriptors_b` of
image j. Feeding `descriptors_a` and `descriptors_b` to `match.brute_force` maps the matcher
over every pair — in parallel, cached pair by pair, and spread over a cluster with `--ray`.

Example:
    "pairs": (op: "sfm.pair_lists",
              inputs: { "keypoints": "features.keypoints", "descriptors": "features.descriptors" },
              params: (selection: "sequential", window: 3)),
    "match": (op: "match.brute_force",
              inputs: { "query": "pairs.descriptors_a", "train": "pairs.descriptors_b" }),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "keypoints",
                PortType::Keypoints.list_of(),
                "Keypoints of every image.",
            ),
            PortSpec::new(
                "descriptors",
                PortType::Descriptors.list_of(),
                "Descriptors of every image, one per keypoint.",
            ),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "pairs",
                PortType::Matrix,
                "N×2: image indices i, j per pair.",
            ),
            PortSpec::new(
                "keypoints_a",
                PortType::Keypoints.list_of(),
                "Keypoints of image i of each pair.",
            ),
            PortSpec::new(
                "keypoints_b",
                PortType::Keypoints.list_of(),
                "Keypoints of image j of each pair.",
            ),
            PortSpec::new(
                "descriptors_a",
                PortType::Descriptors.list_of(),
                "Descriptors of image i of each pair.",
            ),
            PortSpec::new(
                "descriptors_b",
                PortType::Descriptors.list_of(),
                "Descriptors of image j of each pair.",
            ),
        ]
    }

    fn new(p: PairListsParams) -> Result<Self, String> {
        if !p.ratio.is_finite() || p.ratio <= 0.0 {
            return Err(format!("`ratio` must be finite and > 0, got {}", p.ratio));
        }
        Ok(PairLists {
            options: PairOptions {
                selection: p.selection,
                window: p.window as usize,
                neighbors: p.neighbors as usize,
                retrieval_features: p.retrieval_features as usize,
                ratio: p.ratio,
                ..PairOptions::default()
            },
        })
    }
}

impl Operator for PairLists {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let keypoints = keypoint_lists(inputs, "keypoints")?;
        let descriptors: Vec<&Descriptors> =
            required_list(inputs, "descriptors", PortType::Descriptors, |v| match v {
                Value::Descriptors(d) => Some(&**d),
                _ => None,
            })?;
        if keypoints.len() != descriptors.len() {
            return Err(OpError::input(
                "descriptors",
                format!(
                    "{} descriptor sets for {} keypoint sets",
                    descriptors.len(),
                    keypoints.len()
                ),
            ));
        }
        let pairs =
            select_pairs(&descriptors, &keypoints, &self.options).map_err(OpError::failed)?;
        let keypoint_values = required_list(inputs, "keypoints", PortType::Keypoints, Some)?;
        let descriptor_values = required_list(inputs, "descriptors", PortType::Descriptors, Some)?;
        let pick = |values: &[&Value], side: fn(&(usize, usize)) -> usize| -> Vec<Value> {
            pairs.iter().map(|p| values[side(p)].clone()).collect()
        };
        let matrix = Matrix::new(
            pairs.len(),
            2,
            pairs
                .iter()
                .flat_map(|&(i, j)| [i as f64, j as f64])
                .collect(),
        )
        .map_err(|e| OpError::failed(e.to_string()))?;
        Ok(Outputs::new()
            .with("pairs", Value::Matrix(matrix.into()))
            .with(
                "keypoints_a",
                Value::list(PortType::Keypoints, pick(&keypoint_values, |p| p.0)),
            )
            .with(
                "keypoints_b",
                Value::list(PortType::Keypoints, pick(&keypoint_values, |p| p.1)),
            )
            .with(
                "descriptors_a",
                Value::list(PortType::Descriptors, pick(&descriptor_values, |p| p.0)),
            )
            .with(
                "descriptors_b",
                Value::list(PortType::Descriptors, pick(&descriptor_values, |p| p.1)),
            ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ocellus_engine::value::Keypoint;
    use std::sync::Arc;

    fn run(selection: &str, window: u32, n: usize) -> Outputs {
        let kp = |i: usize| {
            Value::Keypoints(Arc::new(vec![Keypoint {
                x: i as f32,
                y: 0.0,
                size: 1.0,
                angle: 0.0,
                response: 1.0,
                octave: 0,
            }]))
        };
        let desc = |i: usize| {
            Value::Descriptors(Arc::new(Descriptors::Binary {
                bytes: 1,
                data: vec![i as u8],
            }))
        };
        let values = [
            Some(Value::list(PortType::Keypoints, (0..n).map(kp).collect())),
            Some(Value::list(
                PortType::Descriptors,
                (0..n).map(desc).collect(),
            )),
        ];
        let specs = PairLists::inputs();
        let op = PairLists::new(PairListsParams {
            selection: match selection {
                "sequential" => PairSelection::Sequential,
                _ => PairSelection::Exhaustive,
            },
            window,
            ..PairListsParams::default()
        })
        .unwrap();
        let ctx = RunContext {
            node: "pairs".into(),
            threads: 1,
            element: None,
        };
        op.run(&ctx, &Inputs::new(&specs, &values)).unwrap()
    }

    fn pair_rows(out: &Outputs) -> Vec<(usize, usize)> {
        let Some(Value::Matrix(m)) = out.get("pairs") else {
            panic!("no pairs")
        };
        m.data
            .chunks(2)
            .map(|r| (r[0] as usize, r[1] as usize))
            .collect()
    }

    #[test]
    fn exhaustive_lists_every_pair_with_its_sides() {
        let out = run("exhaustive", 5, 4);
        let rows = pair_rows(&out);
        assert_eq!(rows, vec![(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]);
        for (name, side) in [("keypoints_a", 0), ("keypoints_b", 1)] {
            let Some(Value::List(list)) = out.get(name) else {
                panic!("{name}")
            };
            assert_eq!(list.items.len(), rows.len());
            for (item, row) in list.items.iter().zip(&rows) {
                let Value::Keypoints(k) = item else { panic!() };
                let image = if side == 0 { row.0 } else { row.1 };
                assert_eq!(k[0].x, image as f32);
            }
        }
        let Some(Value::List(list)) = out.get("descriptors_b") else {
            panic!()
        };
        let firsts: Vec<u8> = list
            .items
            .iter()
            .map(|d| match d {
                Value::Descriptors(d) => match d.as_ref() {
                    Descriptors::Binary { data, .. } => data[0],
                    Descriptors::Float { .. } => 255,
                },
                _ => 255,
            })
            .collect();
        assert_eq!(firsts, vec![1, 2, 3, 2, 3, 3]);
    }

    #[test]
    fn sequential_window_counts() {
        // n images, window w: sum over i of min(w, n - 1 - i).
        let out = run("sequential", 3, 10);
        assert_eq!(pair_rows(&out).len(), 3 * 7 + 2 + 1);
        let out = run("sequential", 3, 1);
        assert!(pair_rows(&out).is_empty());
    }
}
