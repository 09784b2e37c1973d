//! Cost of calling an operator through a loaded plugin (C ABI, views in, host-allocated buffers
//! out) against the same work as a static built-in. Builds `ocellus-plugin-minimal` in release
//! mode into `target/plugin-bench` first.
//!
//! - `scalar`: `minimal.guard` (y = x) vs a built-in y = x — pure boundary overhead.
//! - `invert_8x8`: `minimal.invert` on an 8×8 RGB image (one `parallel_for` task on the host
//!   pool, one output buffer) vs the same loop as a built-in.
//!
//! `cargo bench -p ocellus-engine --bench plugin_call`

use std::hint::black_box;
use std::path::PathBuf;
use std::process::Command;

use criterion::{Criterion, criterion_group, criterion_main};
use ocellus_engine::{
    Channels, Image, Inputs, NoParams, Op, OpError, Operator, Outputs, ParamMap, PortSpec,
    PortType, Registry, RunContext, Value, load_plugin,
};

struct Same;

impl Operator for Same {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        Ok(Outputs::new().with("y", Value::Scalar(inputs.scalar("x")?)))
    }
}

impl Op for Same {
    type Params = NoParams;
    const ID: &'static str = "bench.same";
    const SUMMARY: &'static str = "y = x";
    const DOC: &'static str = "Static twin of `minimal.guard`.";
    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new("x", PortType::Scalar, "input")]
    }
    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new("y", PortType::Scalar, "output")]
    }
    fn new(_: NoParams) -> Result<Self, String> {
        Ok(Same)
    }
}

struct Invert;

impl Operator for Invert {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let samples = image
            .as_u8()
            .ok_or_else(|| OpError::input("image", "expected u8"))?;
        let inverted: Vec<u8> = samples.iter().map(|v| 255 - v).collect();
        let out = Image::from_u8(image.width(), image.height(), image.channels(), inverted)
            .map_err(|e| OpError::failed(e.to_string()))?;
        Ok(Outputs::new().with("image", Value::image(out)))
    }
}

impl Op for Invert {
    type Params = NoParams;
    const ID: &'static str = "bench.invert";
    const SUMMARY: &'static str = "255 − v";
    const DOC: &'static str = "Static twin of `minimal.invert`.";
    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new("image", PortType::Image, "input")]
    }
    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new("image", PortType::Image, "output")]
    }
    fn new(_: NoParams) -> Result<Self, String> {
        Ok(Invert)
    }
}

fn plugin_library() -> PathBuf {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..");
    let target = root.join("target").join("plugin-bench");
    let status = Command::new(env!("CARGO"))
        .args([
            "build",
            "--quiet",
            "--release",
            "-p",
            "ocellus-plugin-minimal",
        ])
        .arg("--target-dir")
        .arg(&target)
        .current_dir(&root)
        .status();
    assert!(
        status.is_ok_and(|s| s.success()),
        "building the minimal plugin failed"
    );
    target.join("release").join(format!(
        "{}ocellus_plugin_minimal{}",
        std::env::consts::DLL_PREFIX,
        std::env::consts::DLL_SUFFIX
    ))
}

fn bench(c: &mut Criterion) {
    let mut registry = Registry::new();
    registry.register::<Same>().unwrap_or_default();
    registry.register::<Invert>().unwrap_or_default();
    if let Err(e) = load_plugin(&plugin_library(), &mut registry) {
        panic!("{e}");
    }
    let ctx = RunContext {
        node: "bench".into(),
        threads: 1,
        element: None,
    };
    let build = |id: &str| match registry
        .get(id)
        .map(|f| (f.info().clone(), f.build(&ParamMap::new())))
    {
        Some((info, Ok(op))) => (info, op),
        _ => panic!("cannot build {id}"),
    };

    let scalar = [Some(Value::Scalar(3.0))];
    let mut group = c.benchmark_group("scalar");
    for id in ["bench.same", "minimal.guard"] {
        let (info, op) = build(id);
        group.bench_function(id, |b| {
            b.iter(|| black_box(op.run(&ctx, &Inputs::new(&info.inputs, black_box(&scalar)))))
        });
    }
    group.finish();

    let image = match Image::from_u8(8, 8, Channels::Rgb, (0..192u8).collect()) {
        Ok(i) => [Some(Value::image(i))],
        Err(e) => panic!("{e}"),
    };
    let mut group = c.benchmark_group("invert_8x8");
    for id in ["bench.invert", "minimal.invert"] {
        let (info, op) = build(id);
        group.bench_function(id, |b| {
            b.iter(|| black_box(op.run(&ctx, &Inputs::new(&info.inputs, black_box(&image)))))
        });
    }
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
