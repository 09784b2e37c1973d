//! `ocellus ops`: the operator reference, generated from the registry (ids, ports, params with
//! types, defaults, ranges, units and docs).

use std::process::ExitCode;

use ocellus_engine::diag::suggest;
use ocellus_engine::{OpInfo, ParamSpec, ParamValue, PortSpec, Registry};
use serde_json::Value as Json;

/// Lists all operators, or one in full; `json` for machine-readable output.
pub fn ops(registry: &Registry, op: Option<&str>, json: bool) -> ExitCode {
    let infos: Vec<&OpInfo> = match op {
        None => registry.iter().map(|f| f.info()).collect(),
        Some(id) => match registry.get(id) {
            Some(f) => vec![f.info()],
            None => {
                let hint = suggest(id, registry.ids())
                    .map(|s| format!(" (did you mean `{s}`?)"))
                    .unwrap_or_default();
                eprintln!("error: unknown operator `{id}`{hint}");
                return ExitCode::from(crate::cli::EXIT_INVALID);
            }
        },
    };
    if json {
        let list: Vec<Json> = infos.iter().map(|i| op_json(i)).collect();
        let doc = if op.is_some() {
            list.into_iter().next().unwrap_or(Json::Null)
        } else {
            Json::Array(list)
        };
        match serde_json::to_string_pretty(&doc) {
            Ok(text) => println!("{text}"),
            Err(e) => {
                eprintln!("error: {e}");
                return ExitCode::from(crate::cli::EXIT_FAILED);
            }
        }
    } else if op.is_some() {
        for info in infos {
            print!("{}", op_text(info));
        }
    } else {
        let width = infos.iter().map(|i| i.id.len()).max().unwrap_or(0);
        let mut family = "";
        for info in infos {
            if info.family() != family {
                family = info.family();
                println!("{family}");
            }
            println!("  {:width$}  {}", info.id, info.summary);
        }
        println!("\n`ocellus ops OP` shows one operator in full; `--json` for tools.");
    }
    ExitCode::SUCCESS
}

/// The JSON description of one operator (what `ocellus ops --json` prints for it).
pub fn op_json(info: &OpInfo) -> Json {
    ocellus_engine::reference::op_json(info)
}

fn default_text(p: &ParamSpec) -> String {
    match &p.default {
        ParamValue::Str(s) if s.is_empty() => "(required)".into(),
        other => other.to_string(),
    }
}

fn op_text(info: &OpInfo) -> String {
    let mut out = format!(
        "{} (v{}, {})\n  {}\n\n",
        info.id, info.version, info.origin, info.summary
    );
    for line in wrap(&info.doc, 96) {
        out.push_str(&format!("  {line}\n"));
    }
    let ports = |title: &str, ports: &[PortSpec], out: &mut String| {
        if ports.is_empty() {
            return;
        }
        out.push_str(&format!("\n{title}:\n"));
        for p in ports {
            let opt = if p.optional { " (optional)" } else { "" };
            out.push_str(&format!(
                "  {:<12} {:<16} {}{opt}\n",
                p.name,
                p.ty.to_string(),
                p.doc
            ));
        }
    };
    ports("inputs", &info.inputs, &mut out);
    ports("outputs", &info.outputs, &mut out);
    if !info.params.is_empty() {
        out.push_str("\nparams:\n");
        for p in &info.params {
            let unit = if p.unit.is_empty() {
                String::new()
            } else {
                format!(" [{}]", p.unit)
            };
            let range = p.range_text().map(|r| format!(", {r}")).unwrap_or_default();
            out.push_str(&format!(
                "  {}: {}{unit} = {}{range}\n",
                p.name,
                p.ty,
                default_text(p)
            ));
            for line in wrap(&p.doc, 90) {
                out.push_str(&format!("      {line}\n"));
            }
        }
    }
    out.push('\n');
    out
}

/// Greedy word wrap.
fn wrap(text: &str, width: usize) -> Vec<String> {
    let mut lines = Vec::new();
    for paragraph in text.split('\n') {
        let mut line = String::new();
        for word in paragraph.split_whitespace() {
            if !line.is_empty() && line.len() + 1 + word.len() > width {
                lines.push(std::mem::take(&mut line));
            }
            if !line.is_empty() {
                line.push(' ');
            }
            line.push_str(word);
        }
        lines.push(line);
    }
    while lines.last().is_some_and(String::is_empty) {
        lines.pop();
    }
    lines
}
