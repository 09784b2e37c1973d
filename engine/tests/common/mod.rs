//! Tiny operators for testing the engine without the built-in ones: every call is counted, so
//! tests can assert exactly which nodes ran.

#![allow(dead_code, clippy::unwrap_used, clippy::expect_used)]

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};

use ocellus_engine::diag::SourceFile;
use ocellus_engine::op::{OpFactory, OpInfo, Origin};
use ocellus_engine::{
    Graph, Inputs, OpError, Operator, Outputs, ParamMap, ParamSpec, ParamValue, PortSpec, PortType,
    Registry, RunContext, Value,
};

/// Calls per operator id.
#[derive(Clone, Default)]
pub struct Calls(Arc<Mutex<BTreeMap<String, usize>>>);

impl Calls {
    pub fn get(&self, id: &str) -> usize {
        self.0.lock().unwrap().get(id).copied().unwrap_or(0)
    }
    pub fn total(&self) -> usize {
        self.0.lock().unwrap().values().sum()
    }
    fn bump(&self, id: &str) {
        *self.0.lock().unwrap().entry(id.to_string()).or_default() += 1;
    }
}

type RunFn = Arc<dyn Fn(&ParamMap, &Inputs<'_>) -> Result<Outputs, OpError> + Send + Sync>;

struct TestFactory {
    info: OpInfo,
    calls: Calls,
    run: RunFn,
}

struct TestOp {
    id: String,
    params: ParamMap,
    calls: Calls,
    run: RunFn,
}

impl Operator for TestOp {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        self.calls.bump(&self.id);
        (self.run)(&self.params, inputs)
    }
}

impl OpFactory for TestFactory {
    fn info(&self) -> &OpInfo {
        &self.info
    }
    fn build(&self, params: &ParamMap) -> Result<Arc<dyn Operator>, String> {
        if let Some(ParamValue::Float(x)) = params.get("value")
            && *x == 13.0
        {
            return Err("13 is unlucky".into());
        }
        Ok(Arc::new(TestOp {
            id: self.info.id.clone(),
            params: params.clone(),
            calls: self.calls.clone(),
            run: Arc::clone(&self.run),
        }))
    }
}

fn info(id: &str, inputs: Vec<PortSpec>, outputs: Vec<PortSpec>, params: Vec<ParamSpec>) -> OpInfo {
    OpInfo {
        id: id.into(),
        version: 1,
        summary: format!("test operator {id}"),
        doc: String::new(),
        inputs,
        outputs,
        params,
        side_effects: false,
        origin: Origin::Static("tests".into()),
    }
}

fn float(params: &ParamMap, name: &str) -> f64 {
    match params.get(name) {
        Some(ParamValue::Float(x)) => *x,
        _ => f64::NAN,
    }
}

/// `t.source(value) -> value: Scalar`, `t.add(a, b?) -> sum`, `t.repeat(x; count) -> items:
/// List<Scalar>`, `t.fail(x) -> y` (always fails), `t.panic(x) -> y`, `t.collect(items:
/// List<Scalar>) -> total`.
pub fn registry() -> (Registry, Calls) {
    let calls = Calls::default();
    let mut reg = Registry::new();
    let mut add = |info: OpInfo, run: RunFn| {
        reg.register_factory(Arc::new(TestFactory {
            info,
            calls: calls.clone(),
            run,
        }))
        .unwrap();
    };
    let scalar = |n: &str| PortSpec::new(n, PortType::Scalar, "a number");
    add(
        info(
            "t.source",
            vec![],
            vec![scalar("value")],
            vec![
                ParamSpec::new("value", &0.0f64, "the value")
                    .min(-1000.0)
                    .max(1000.0)
                    .unit("px"),
            ],
        ),
        Arc::new(|p, _| Ok(Outputs::new().with("value", Value::Scalar(float(p, "value"))))),
    );
    add(
        info(
            "t.add",
            vec![scalar("a"), scalar("b").optional()],
            vec![scalar("sum")],
            vec![ParamSpec::new("offset", &0.0f64, "added too")],
        ),
        Arc::new(|p, inputs| {
            let b = if inputs.get("b").is_some() {
                inputs.scalar("b")?
            } else {
                0.0
            };
            Ok(Outputs::new().with(
                "sum",
                Value::Scalar(inputs.scalar("a")? + b + float(p, "offset")),
            ))
        }),
    );
    add(
        info(
            "t.repeat",
            vec![scalar("x")],
            vec![PortSpec::new("items", PortType::Scalar.list_of(), "copies")],
            vec![ParamSpec::new("count", &3u32, "how many")],
        ),
        Arc::new(|p, inputs| {
            let x = inputs.scalar("x")?;
            let n = match p.get("count") {
                Some(ParamValue::Int(n)) => *n as usize,
                _ => 0,
            };
            let items = (0..n).map(|k| Value::Scalar(x + k as f64)).collect();
            Ok(Outputs::new().with("items", Value::list(PortType::Scalar, items)))
        }),
    );
    add(
        info("t.fail", vec![scalar("x")], vec![scalar("y")], vec![]),
        Arc::new(|_, _| Err(OpError::failed("deliberate failure"))),
    );
    add(
        info("t.panic", vec![scalar("x")], vec![scalar("y")], vec![]),
        Arc::new(|_, _| panic!("deliberate panic")),
    );
    add(
        info(
            "t.collect",
            vec![PortSpec::new(
                "items",
                PortType::Scalar.list_of(),
                "numbers",
            )],
            vec![scalar("total")],
            vec![],
        ),
        Arc::new(|_, inputs| {
            let Some(Value::List(list)) = inputs.get("items") else {
                return Err(OpError::input("items", "not a list"));
            };
            let total = list
                .items
                .iter()
                .map(|v| if let Value::Scalar(x) = v { *x } else { 0.0 })
                .sum();
            Ok(Outputs::new().with("total", Value::Scalar(total)))
        }),
    );
    (reg, calls)
}

pub fn source(name: &str, text: &str) -> Arc<SourceFile> {
    SourceFile::new(name, None, text)
}

pub fn load(reg: &Registry, text: &str) -> Graph {
    match ocellus_engine::resolve::load_source(reg, &source("test.ron", text), &[]) {
        Ok(g) => g,
        Err(d) => panic!("graph did not load:\n{d}"),
    }
}

pub fn errors(reg: &Registry, text: &str) -> Vec<String> {
    match ocellus_engine::resolve::load_source(reg, &source("test.ron", text), &[]) {
        Ok(_) => panic!("graph loaded but errors were expected"),
        Err(d) => {
            d.0.iter()
                .map(|d| format!("{}: {}", d.location().unwrap_or_default(), d.message))
                .collect()
        }
    }
}

pub fn count(counter: &AtomicUsize) -> usize {
    counter.load(Ordering::SeqCst)
}

/// A fresh empty folder under the system temp dir.
pub fn temp_dir(tag: &str) -> std::path::PathBuf {
    static NEXT: AtomicUsize = AtomicUsize::new(0);
    let dir = std::env::temp_dir().join(format!(
        "ocellus-test-{tag}-{}-{}",
        std::process::id(),
        NEXT.fetch_add(1, Ordering::SeqCst)
    ));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}
