//! Scheduler overhead: a chain of 1,000 trivial nodes (each adds 1 to a number), so almost all
//! time is the engine's own — planning, keying, spawning, handing values on, releasing them.
//! Divide the per-run time by 1,000 for the per-node overhead.
//!
//! `cargo bench -p ocellus-engine --bench scheduler`

use std::hint::black_box;
use std::sync::Arc;

use criterion::{Criterion, criterion_group, criterion_main};
use ocellus_engine::diag::SourceFile;
use ocellus_engine::resolve::load_source;
use ocellus_engine::{
    Inputs, NoParams, Op, OpError, Operator, Outputs, PortSpec, PortType, Registry, RunContext,
    RunOptions, Value, run,
};

struct AddOne;

impl Operator for AddOne {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let x = match inputs.get("x") {
            Some(_) => inputs.scalar("x")?,
            None => 0.0,
        };
        Ok(Outputs::new().with("y", Value::Scalar(x + 1.0)))
    }
}

impl Op for AddOne {
    type Params = NoParams;
    const ID: &'static str = "bench.add_one";
    const SUMMARY: &'static str = "y = x + 1";
    const DOC: &'static str = "Trivial operator for scheduler benchmarks.";
    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new("x", PortType::Scalar, "input").optional()]
    }
    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new("y", PortType::Scalar, "output")]
    }
    fn new(_: NoParams) -> Result<Self, String> {
        Ok(AddOne)
    }
}

fn chain_graph(n: usize) -> String {
    let mut text = String::from("Graph(nodes: {\n    \"n0\": (op: \"bench.add_one\"),\n");
    for i in 1..n {
        text.push_str(&format!(
            "    \"n{i}\": (op: \"bench.add_one\", inputs: {{ \"x\": \"n{}.y\" }}),\n",
            i - 1
        ));
    }
    text.push_str(&format!("}}, outputs: {{ \"last\": \"n{}.y\" }})", n - 1));
    text
}

/// Many independent chains side by side (fan-out), to measure spawning across workers.
fn wide_graph(chains: usize, depth: usize) -> String {
    let mut text = String::from("Graph(nodes: {\n");
    let mut outputs = String::new();
    for c in 0..chains {
        text.push_str(&format!("    \"c{c}_0\": (op: \"bench.add_one\"),\n"));
        for d in 1..depth {
            text.push_str(&format!(
                "    \"c{c}_{d}\": (op: \"bench.add_one\", inputs: {{ \"x\": \"c{c}_{}.y\" }}),\n",
                d - 1
            ));
        }
        outputs.push_str(&format!("\"o{c}\": \"c{c}_{}.y\", ", depth - 1));
    }
    text.push_str(&format!("}}, outputs: {{ {outputs} }})"));
    text
}

fn bench(c: &mut Criterion) {
    let mut registry = Registry::new();
    if registry.register::<AddOne>().is_err() {
        return;
    }
    let chain = match load_source(
        &registry,
        &SourceFile::new("chain.ron", None, chain_graph(1000)),
        &[],
    ) {
        Ok(g) => Arc::new(g),
        Err(d) => panic!("{d}"),
    };
    let wide = match load_source(
        &registry,
        &SourceFile::new("wide.ron", None, wide_graph(10, 100)),
        &[],
    ) {
        Ok(g) => Arc::new(g),
        Err(d) => panic!("{d}"),
    };
    for threads in [1, 2] {
        let options = RunOptions {
            threads,
            ..RunOptions::default()
        };
        c.bench_function(&format!("chain_1000_nodes_threads_{threads}"), |b| {
            b.iter(|| black_box(run(&chain, &options)))
        });
        c.bench_function(&format!("wide_10x100_nodes_threads_{threads}"), |b| {
            b.iter(|| black_box(run(&wide, &options)))
        });
    }
    c.bench_function("load_and_validate_chain_1000", |b| {
        let text = chain_graph(1000);
        b.iter(|| {
            black_box(
                load_source(
                    &registry,
                    &SourceFile::new("chain.ron", None, text.clone()),
                    &[],
                )
                .is_ok(),
            )
        })
    });
}

criterion_group!(benches, bench);
criterion_main!(benches);
