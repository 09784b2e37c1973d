//! A minimal Ocellus plugin: `minimal.invert` (an image operator running on the host's thread
//! pool), `minimal.guard` (fails or panics on request, to test failure isolation) and
//! `minimal.stats` (several outputs of several types).
//!
//! Build with `cargo build --release -p ocellus-plugin-minimal`, then
//! `ocellus run graph.ron --plugin target/release/libocellus_plugin_minimal.so`.

use std::sync::Mutex;

use ocellus_plugin::{
    Context, InputViews, OutputValues, Param, Params, PluginOp, Port, PortType, Samples,
};

/// Rows handed to one task of the host's thread pool.
const ROWS_PER_TASK: usize = 64;

/// `minimal.invert`: `255 − v` for every sample of an 8-bit image.
pub struct Invert;

impl PluginOp for Invert {
    const ID: &'static str = "minimal.invert";
    const SUMMARY: &'static str = "Inverts an 8-bit image: 255 − v for every sample.";
    const DOC: &'static str = "Every sample v of every channel becomes 255 − v. Rows are processed \
        in chunks of 64 on the host's thread pool.\n\nExample: `(op: \"minimal.invert\", inputs: \
        { \"image\": \"card.image\" })`";
    const INPUTS: &'static [Port] = &[Port::new(
        "image",
        PortType::Image,
        "8-bit image, any channels",
    )];
    const OUTPUTS: &'static [Port] = &[Port::new("image", PortType::Image, "the inverted image")];

    fn new(_params: &Params) -> Result<Self, String> {
        Ok(Invert)
    }

    fn run(&self, ctx: &Context, inputs: &InputViews) -> Result<OutputValues, String> {
        let image = inputs.image("image")?;
        if !matches!(image.samples, Samples::U8(_)) {
            return Err(format!(
                "input `image`: expected u8 samples, got {}",
                image.depth_name()
            ));
        }
        let row_len = image.width * image.channels;
        let tasks = image.height.div_ceil(ROWS_PER_TASK);
        let chunks: Vec<Mutex<Vec<u8>>> = (0..tasks).map(|_| Mutex::new(Vec::new())).collect();
        ctx.parallel_for(tasks, |task| {
            let rows = task * ROWS_PER_TASK..((task + 1) * ROWS_PER_TASK).min(image.height);
            let mut out = Vec::with_capacity(rows.len() * row_len);
            for y in rows {
                let row = image.row_u8(y).unwrap_or_default();
                out.extend(row.iter().map(|v| 255 - v));
            }
            if let Ok(mut slot) = chunks[task].lock() {
                *slot = out;
            }
        });
        let mut samples = Vec::with_capacity(image.height * row_len);
        for chunk in chunks {
            samples.extend(chunk.into_inner().map_err(|_| "a task failed")?);
        }
        Ok(OutputValues::new().image_u8(
            "image",
            image.width,
            image.height,
            image.channels,
            samples,
        ))
    }
}

/// `minimal.guard`: passes a number through, or fails or panics on request.
pub struct Guard {
    panic: bool,
    fail: bool,
}

impl PluginOp for Guard {
    const ID: &'static str = "minimal.guard";
    const SUMMARY: &'static str = "Passes a number through; fails or panics on request.";
    const DOC: &'static str = "y = x. With `fail: true` the call returns an error, with \
        `panic: true` it panics: both become a node error naming the plugin, and the other \
        branches of the graph still run.";
    const INPUTS: &'static [Port] = &[Port::new("x", PortType::Scalar, "a number")];
    const OUTPUTS: &'static [Port] = &[Port::new("y", PortType::Scalar, "the same number")];
    const PARAMS: &'static [Param] = &[
        Param::bool("panic", false, "panic when run"),
        Param::bool("fail", false, "return an error when run"),
    ];

    fn new(params: &Params) -> Result<Self, String> {
        Ok(Guard {
            panic: params.bool("panic")?,
            fail: params.bool("fail")?,
        })
    }

    fn run(&self, _ctx: &Context, inputs: &InputViews) -> Result<OutputValues, String> {
        let x = inputs.scalar("x")?;
        if self.panic {
            panic!("guard asked to panic (x = {x})");
        }
        if self.fail {
            return Err(format!("guard asked to fail (x = {x})"));
        }
        Ok(OutputValues::new().scalar("y", x))
    }
}

/// `minimal.stats`: several outputs of several types from one image.
pub struct Stats {
    label: String,
}

impl PluginOp for Stats {
    const ID: &'static str = "minimal.stats";
    const SUMMARY: &'static str =
        "Mean and pixel count of an 8-bit image, as numbers, text and metrics.";
    const DOC: &'static str = "mean = Σv / n over all samples; pixels = width × height.";
    const INPUTS: &'static [Port] = &[Port::new("image", PortType::Image, "8-bit image")];
    const OUTPUTS: &'static [Port] = &[
        Port::new("mean", PortType::Scalar, "mean sample value"),
        Port::new("pixels", PortType::Integer, "width × height"),
        Port::new("text", PortType::Text, "`LABEL: mean M over N pixels`"),
        Port::new("metrics", PortType::Metrics, "`mean` and `pixels`"),
    ];
    const PARAMS: &'static [Param] = &[Param::string("label", "stats", "prefix of `text`")];

    fn new(params: &Params) -> Result<Self, String> {
        Ok(Stats {
            label: params.string("label")?.to_string(),
        })
    }

    fn run(&self, _ctx: &Context, inputs: &InputViews) -> Result<OutputValues, String> {
        let image = inputs.image("image")?;
        let mut sum = 0u64;
        let mut count = 0u64;
        for y in 0..image.height {
            let row = image.row_u8(y).ok_or_else(|| {
                format!(
                    "input `image`: expected u8 samples, got {}",
                    image.depth_name()
                )
            })?;
            sum += row.iter().map(|&v| u64::from(v)).sum::<u64>();
            count += row.len() as u64;
        }
        let mean = if count == 0 {
            0.0
        } else {
            sum as f64 / count as f64
        };
        let pixels = i64::try_from(image.width * image.height).unwrap_or(i64::MAX);
        Ok(OutputValues::new()
            .scalar("mean", mean)
            .integer("pixels", pixels)
            .text(
                "text",
                format!("{}: mean {mean:.3} over {pixels} pixels", self.label),
            )
            .metrics(
                "metrics",
                vec![("mean".into(), mean), ("pixels".into(), pixels as f64)],
            ))
    }
}

ocellus_plugin::export_plugin!(name: "minimal", ops: [Invert, Guard, Stats]);
