//! `ocellus run GRAPH --ray ADDRESS`: the graph runs here, and its distributable list maps run
//! as Ray tasks. Ray is driven from Python, so this starts the package's driver
//! (`python -m ocellus.ray_driver`, from the `ocellus` Python package) and talks to it over its
//! stdin and stdout; the protocol is described in `python/ocellus/ray_driver.py`.
//!
//! The interpreter is `$OCELLUS_PYTHON`, else `python3`.

use std::io::{BufReader, BufWriter, Read, Write};
use std::path::PathBuf;
use std::process::{Child, ChildStdin, ChildStdout, Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

use ocellus_engine::distribute::{Distribution, Stage, TaskDone, TaskRunner};
use serde_json::{Value as Json, json};

/// The driver process and its pipes; one stage talks to it at a time.
pub struct RayDriver {
    pipes: Mutex<Pipes>,
    child: Mutex<Child>,
    /// Set when the protocol went out of step: the driver is killed and every later stage fails
    /// (never reading another stage's leftover frames as its own).
    broken: AtomicBool,
}

struct Pipes {
    to: BufWriter<ChildStdin>,
    from: BufReader<ChildStdout>,
}

/// Largest frame accepted from the driver (a chunk's results), bytes.
const MAX_FRAME: u64 = 1 << 34;

fn write_frame(w: &mut impl Write, data: &[u8]) -> std::io::Result<()> {
    w.write_all(&(data.len() as u64).to_le_bytes())?;
    w.write_all(data)
}

fn read_frame(r: &mut impl Read) -> Result<Vec<u8>, String> {
    let mut head = [0u8; 8];
    r.read_exact(&mut head)
        .map_err(|e| format!("the Ray driver stopped answering: {e}"))?;
    let n = u64::from_le_bytes(head);
    if n > MAX_FRAME {
        return Err(format!("the Ray driver sent a frame of {n} bytes"));
    }
    let mut data = Vec::new();
    r.take(n)
        .read_to_end(&mut data)
        .map_err(|e| format!("the Ray driver stopped answering: {e}"))?;
    if data.len() as u64 != n {
        return Err("the Ray driver stopped mid-frame".into());
    }
    Ok(data)
}

fn read_json(r: &mut impl Read) -> Result<Json, String> {
    let frame = read_frame(r)?;
    serde_json::from_slice(&frame).map_err(|e| format!("the Ray driver sent bad JSON: {e}"))
}

impl RayDriver {
    /// Starts the driver and waits until it has joined the cluster at `address`.
    pub fn start(address: &str) -> Result<RayDriver, String> {
        let python = std::env::var_os("OCELLUS_PYTHON").unwrap_or_else(|| "python3".into());
        let mut child = Command::new(&python)
            .args(["-m", "ocellus.ray_driver", "--address", address])
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .map_err(|e| {
                format!(
                    "--ray needs Python with the `ocellus` package (pip install ocellus[ray]); \
                     cannot start {}: {e}",
                    PathBuf::from(&python).display()
                )
            })?;
        let (Some(to), Some(from)) = (child.stdin.take(), child.stdout.take()) else {
            return Err("cannot open pipes to the Ray driver".into());
        };
        let mut pipes = Pipes {
            to: BufWriter::new(to),
            from: BufReader::new(from),
        };
        let hello = match read_json(&mut pipes.from) {
            Ok(h) => h,
            Err(e) => {
                let _ = child.kill();
                let status = child.wait().ok();
                return Err(format!(
                    "the Ray driver (`{} -m ocellus.ray_driver`) did not start ({e}{}); is the \
                     `ocellus` Python package installed with Ray?",
                    PathBuf::from(&python).display(),
                    status.map(|s| format!(", {s}")).unwrap_or_default()
                ));
            }
        };
        if let Some(error) = hello.get("error").and_then(Json::as_str) {
            let _ = child.wait();
            return Err(format!("cannot join the Ray cluster at {address}: {error}"));
        }
        tracing::info!("joined the Ray cluster at {address}: {hello}");
        Ok(RayDriver {
            pipes: Mutex::new(pipes),
            child: Mutex::new(child),
            broken: AtomicBool::new(false),
        })
    }

    /// The distribution settings for a run through this driver.
    pub fn distribution(
        self: &Arc<Self>,
        items_per_task: usize,
        item_cache: Option<PathBuf>,
    ) -> Distribution {
        Distribution {
            runner: self.clone(),
            items_per_task,
            item_cache,
            progress: Some(Arc::new(|node: &str, done: usize, total: usize| {
                eprintln!("ray: {node}: {done}/{total} items");
            })),
        }
    }

    /// Kills the driver after a protocol error; later stages fail at once.
    fn poison(&self, message: String) -> String {
        self.broken.store(true, Ordering::SeqCst);
        if let Ok(mut child) = self.child.lock() {
            let _ = child.kill();
            let _ = child.wait();
        }
        message
    }

    /// Asks the driver to exit and waits for it.
    pub fn close(&self) {
        if self.broken.load(Ordering::SeqCst) {
            return;
        }
        if let Ok(mut pipes) = self.pipes.lock() {
            let _ = write_frame(&mut pipes.to, b"{}");
            let _ = pipes.to.flush();
        }
        if let Ok(mut child) = self.child.lock() {
            let _ = child.wait();
        }
    }
}

impl TaskRunner for RayDriver {
    fn run(
        &self,
        stage: &Stage,
        tasks: Vec<Vec<u8>>,
        done: &mut dyn FnMut(TaskDone) -> Result<(), String>,
    ) -> Result<(), String> {
        if self.broken.load(Ordering::SeqCst) {
            return Err("the Ray driver stopped after an earlier error".into());
        }
        let mut pipes = self
            .pipes
            .lock()
            .map_err(|_| "the Ray driver's pipes are unusable".to_string())?;
        let header = json!({
            "node": stage.node, "op": stage.op, "items": stage.items,
            "reused": stage.reused, "tasks": tasks.len(),
        });
        let sent = (|| -> std::io::Result<()> {
            write_frame(&mut pipes.to, header.to_string().as_bytes())?;
            for t in &tasks {
                write_frame(&mut pipes.to, t)?;
            }
            pipes.to.flush()
        })();
        if let Err(e) = sent {
            drop(pipes);
            return Err(self.poison(format!("cannot send tasks to the Ray driver: {e}")));
        }
        drop(tasks);
        // Read to the stage's end even after a failed task, so the next stage starts clean; a
        // frame that makes no sense ends the driver instead.
        let mut outcome = Ok(());
        let protocol = (|| -> Result<(), String> {
            loop {
                let head = read_json(&mut pipes.from)?;
                if head.get("end").is_some() {
                    if let Some(error) = head.get("error").and_then(Json::as_str)
                        && outcome.is_ok()
                    {
                        outcome = Err(format!("the Ray driver: {error}"));
                    }
                    return Ok(());
                }
                let data = read_frame(&mut pipes.from)?;
                let task = head
                    .get("task")
                    .and_then(Json::as_u64)
                    .ok_or("the Ray driver sent a result without a task index")?;
                if outcome.is_err() {
                    continue;
                }
                let ok = head.get("ok").and_then(Json::as_bool).unwrap_or(false);
                let result = if ok {
                    Ok(data)
                } else {
                    Err(String::from_utf8_lossy(&data).into_owned())
                };
                outcome = done(TaskDone {
                    task: task as usize,
                    result,
                    worker: head
                        .get("worker")
                        .and_then(Json::as_str)
                        .unwrap_or("?")
                        .to_string(),
                    seconds: head.get("seconds").and_then(Json::as_f64).unwrap_or(0.0),
                });
            }
        })();
        drop(pipes);
        if let Err(e) = protocol {
            return Err(self.poison(e));
        }
        outcome
    }
}

/// Where `--ray` keeps finished elements: `--cache DIR`/items when given, else
/// `$OCELLUS_ITEM_CACHE`, `$XDG_CACHE_HOME/ocellus/items` or `~/.cache/ocellus/items` (the
/// Python package's default too).
pub fn item_cache(cache: Option<&std::path::Path>) -> Option<PathBuf> {
    if let Some(dir) = cache {
        return Some(dir.join("items"));
    }
    if let Some(dir) = std::env::var_os("OCELLUS_ITEM_CACHE").filter(|d| !d.is_empty()) {
        return Some(PathBuf::from(dir));
    }
    let base = std::env::var_os("XDG_CACHE_HOME")
        .filter(|d| !d.is_empty())
        .map(PathBuf::from)
        .or_else(|| std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".cache")))?;
    Some(base.join("ocellus").join("items"))
}
