//! Every command block of `README.md` and `firmware/README.md`, run as written.
//!
//! The blocks and their markers (`<!-- run: dir=PATH qemu long source=PATH skip=REASON -->` on
//! the line before the fence) are read by [`integration_tests::readme`], whose doc states the
//! rule. Each test copies the files `git ls-files` lists (with their modification times, so that
//! cargo reuses what it built) into a temporary directory, `<tmp>/checkout`, with a symlink
//! `<tmp>/shared` to the real `shared/` (the first one found beside the checkout or above it),
//! and runs each block there with `bash -e -o pipefail`, from the folder its marker names, with
//! the test run's `CARGO_TARGET_DIR` (or the workspace's target directory), in a process group
//! of its own; when the block ends, that group and every process that inherited the block's
//! `PIEZO_README_BLOCK` variable are killed (a QEMU it started in the background). The
//! temporary directory is removed at the end, also on failure.
//!
//! `readme_short_commands_run` runs the blocks not marked `long` (part of `cargo test`);
//! `readme_long_commands_run` (`#[ignore]`d, run by `.ci/run`) runs the `long` ones. Blocks
//! marked `qemu` are skipped with a note when `qemu-system-arm` or the Cortex-M target is
//! missing; `skip=` blocks are listed. A failure names the README, the line of the block, the
//! command, the exit status and the last lines of its stdout and stderr.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

#[allow(dead_code)] // only the temporary directory is used here
mod common;

use common::TempDir;
use integration_tests::qemu::{missing_tools, outer_target_dir, say, workspace};
use integration_tests::readme::{command_blocks, Block, Marker};

/// The READMEs whose blocks run, relative to the repository root.
const READMES: [&str; 2] = ["README.md", "firmware/README.md"];

/// Longest run of one block before it is killed (a short block should take under 30 s).
const SHORT_LIMIT: Duration = Duration::from_secs(15 * 60);
const LONG_LIMIT: Duration = Duration::from_secs(60 * 60);

/// Lines of stdout and stderr shown for a failed block.
const TAIL: usize = 40;

/// Every command block of the READMEs, with its README; panics with the parse error.
fn all_blocks() -> Vec<(&'static str, Block)> {
    let mut out = Vec::new();
    for file in READMES {
        let text = std::fs::read_to_string(workspace().join(file))
            .unwrap_or_else(|e| panic!("read {file}: {e}"));
        let blocks = command_blocks(&text, file).unwrap_or_else(|e| panic!("{e}"));
        out.extend(blocks.into_iter().map(|b| (file, b)));
    }
    out
}

/// The target directory builds share: `CARGO_TARGET_DIR` (relative to the root) or the one
/// this test was built in.
fn target_dir() -> PathBuf {
    match std::env::var_os("CARGO_TARGET_DIR") {
        Some(dir) if !dir.is_empty() => workspace().join(dir),
        _ => outer_target_dir(),
    }
}

/// The `shared/` folder beside the checkout, or beside a folder above it.
fn shared_dir() -> PathBuf {
    let root = workspace();
    root.ancestors()
        .skip(1)
        .map(|a| a.join("shared"))
        .find(|s| s.is_dir())
        .unwrap_or_else(|| panic!("no shared/ beside {} or above it", root.display()))
}

/// `<tmp>/checkout` with the files `git ls-files` lists (modification times kept) and
/// `<tmp>/shared` pointing at the real one; removed when dropped.
fn fresh_copy() -> TempDir {
    let stamp = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap_or_default()
        .as_nanos();
    let tmp =
        TempDir(std::env::temp_dir().join(format!("piezo-readme-{}-{stamp}", std::process::id())));
    let root = workspace();
    let checkout = tmp.0.join("checkout");
    let listed = Command::new("git")
        .args(["ls-files", "-z"])
        .current_dir(&root)
        .output()
        .expect("run git ls-files");
    assert!(
        listed.status.success(),
        "git ls-files in {}: {}",
        root.display(),
        String::from_utf8_lossy(&listed.stderr)
    );
    for name in listed.stdout.split(|b| *b == 0).filter(|n| !n.is_empty()) {
        let name = std::str::from_utf8(name).expect("UTF-8 file name");
        let (from, to) = (root.join(name), checkout.join(name));
        let Ok(meta) = std::fs::symlink_metadata(&from) else {
            continue; // deleted in the working tree
        };
        std::fs::create_dir_all(to.parent().expect("a file has a folder")).unwrap();
        if meta.file_type().is_symlink() {
            let link = std::fs::read_link(&from).unwrap();
            std::os::unix::fs::symlink(link, &to).unwrap();
        } else if meta.is_file() {
            std::fs::copy(&from, &to).unwrap_or_else(|e| panic!("copy {name}: {e}"));
            let copied = std::fs::File::options().write(true).open(&to).unwrap();
            copied.set_modified(meta.modified().unwrap()).unwrap();
        }
    }
    std::os::unix::fs::symlink(shared_dir(), tmp.0.join("shared")).unwrap();
    tmp
}

/// The last `n` lines of a log file.
fn tail(path: &Path, n: usize) -> String {
    let text = std::fs::read_to_string(path).unwrap_or_default();
    let lines: Vec<&str> = text.lines().collect();
    lines[lines.len().saturating_sub(n)..].join("\n")
}

/// The variable every process a block starts inherits: `tag` names the block's run.
const TAG_VARIABLE: &str = "PIEZO_README_BLOCK";

/// Sends `signal` to the process group `group` and to every process whose environment holds
/// `PIEZO_README_BLOCK=tag` (a process that left the group: `timeout`, which `run-qemu.sh`
/// runs QEMU under, puts itself in a group of its own). Processes that are gone are ignored.
fn kill_block(group: u32, tag: &str, signal: &str) {
    let mut targets = vec![format!("-{group}")];
    let wanted = format!("{TAG_VARIABLE}={tag}");
    if let Ok(entries) = std::fs::read_dir("/proc") {
        for entry in entries.flatten() {
            let name = entry.file_name().to_string_lossy().to_string();
            if name.parse::<u32>().is_err() {
                continue;
            }
            let Ok(environ) = std::fs::read(entry.path().join("environ")) else {
                continue;
            };
            if environ.split(|b| *b == 0).any(|v| v == wanted.as_bytes()) {
                targets.push(name);
            }
        }
    }
    let _ = Command::new("kill")
        .arg(signal)
        .arg("--")
        .args(&targets)
        .stderr(Stdio::null())
        .status();
}

/// Runs `block` of `file` in the copy `tmp` (its `n`-th, for the log names); Err with the
/// failure report.
fn run_block(tmp: &Path, file: &str, n: usize, block: &Block) -> Result<(), String> {
    let checkout = tmp.join("checkout");
    let dir = checkout.join(&block.marker.dir);
    if !dir.is_dir() {
        return Err(format!(
            "{file}:{}: dir={} is not a folder of the checkout",
            block.line, block.marker.dir
        ));
    }
    let mut script = String::new();
    let mut sourced = String::new();
    if let Some(source) = &block.marker.source {
        let path = checkout.join(source);
        if !path.is_file() {
            return Err(format!(
                "{file}:{}: source={source} is not a file of the checkout",
                block.line
            ));
        }
        writeln!(script, "source {:?}", path.display().to_string()).unwrap();
        sourced = std::fs::read_to_string(&path).unwrap_or_default();
    }
    script.push_str(&block.script);
    // A port the block serves the link on must be free: else its QEMU fails in the background
    // and its commands talk to whatever holds the port.
    for port in [script.as_str(), sourced.as_str()]
        .iter()
        .flat_map(|text| text.split("--link ").skip(1))
        .filter_map(|rest| rest.split_whitespace().next()?.parse::<u16>().ok())
    {
        if std::net::TcpListener::bind(("127.0.0.1", port)).is_err() {
            return Err(format!(
                "{file}:{}: port {port}, which the block serves the link on, is in use",
                block.line
            ));
        }
    }
    let (script_path, out, err) = (
        tmp.join(format!("block-{n}.sh")),
        tmp.join(format!("block-{n}.out")),
        tmp.join(format!("block-{n}.err")),
    );
    std::fs::write(&script_path, &script).unwrap();
    let tag = format!("{}/{n}", tmp.display());
    let mut command = Command::new("bash");
    command
        .args(["-e", "-o", "pipefail"])
        .arg(&script_path)
        .current_dir(&dir)
        .env("CARGO_TARGET_DIR", target_dir())
        .env(TAG_VARIABLE, &tag)
        .env_remove("PIEZO_PARAMS")
        .stdin(Stdio::null())
        .stdout(std::fs::File::create(&out).unwrap())
        .stderr(std::fs::File::create(&err).unwrap());
    // What cargo sets for this test binary is not what a user's shell has.
    for (key, _) in std::env::vars_os() {
        let key = key.to_string_lossy();
        if [
            "CARGO_PKG_",
            "CARGO_MANIFEST_",
            "CARGO_CRATE_",
            "CARGO_BIN_",
        ]
        .iter()
        .any(|p| key.starts_with(p))
            || key == "CARGO_TARGET_TMPDIR"
            || key == "OUT_DIR"
        {
            command.env_remove(key.as_ref());
        }
    }
    std::os::unix::process::CommandExt::process_group(&mut command, 0);
    let mut child = command.spawn().expect("run bash");
    let group = child.id();
    let limit = if block.marker.long {
        LONG_LIMIT
    } else {
        SHORT_LIMIT
    };
    let started = Instant::now();
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break Some(status);
        }
        if started.elapsed() > limit {
            break None;
        }
        std::thread::sleep(Duration::from_millis(100));
    };
    // Whatever the block left running in the background (QEMU) ends with it.
    kill_block(group, &tag, "-TERM");
    std::thread::sleep(Duration::from_millis(300));
    kill_block(group, &tag, "-KILL");
    let _ = child.wait();
    let outcome = match status {
        Some(s) if s.success() => return Ok(()),
        Some(s) => s.to_string(),
        None => format!("killed after {} s", limit.as_secs()),
    };
    let place = if block.marker.dir.is_empty() {
        "the repository root".to_string()
    } else {
        format!("{}/", block.marker.dir)
    };
    Err(format!(
        "{file}:{} (run from {place}): {outcome}\n--- command\n{}--- last lines of stdout\n{}\n--- last lines of stderr\n{}\n",
        block.line,
        script,
        tail(&out, TAIL),
        tail(&err, TAIL)
    ))
}

/// Runs the blocks marked `long` (`long` true) or not, in a fresh copy; panics with every
/// failure.
fn run_blocks(long: bool) {
    let blocks = all_blocks();
    for (file, b) in blocks.iter().filter(|(_, b)| b.marker.skip.is_some()) {
        say(&format!(
            "not run: {file}:{} ({})",
            b.line,
            b.marker.skip.as_deref().unwrap_or_default()
        ));
    }
    let chosen: Vec<&(&str, Block)> = blocks
        .iter()
        .filter(|(_, b)| b.marker.skip.is_none() && b.marker.long == long)
        .collect();
    let missing = missing_tools();
    let tmp = fresh_copy();
    say(&format!(
        "README commands ({}): {} blocks in {} (CARGO_TARGET_DIR {})",
        if long { "long" } else { "short" },
        chosen.len(),
        tmp.0.display(),
        target_dir().display()
    ));
    // Every block's folder and sourced script, long or short, is in the checkout (a file that
    // is not committed is not there).
    let mut failures: Vec<String> = blocks
        .iter()
        .filter(|(_, b)| b.marker.skip.is_none())
        .flat_map(|(file, b)| {
            let checkout = tmp.0.join("checkout");
            let dir = (!checkout.join(&b.marker.dir).is_dir()).then(|| {
                format!(
                    "{file}:{}: dir={} is not a folder of the checkout",
                    b.line, b.marker.dir
                )
            });
            let source = b.marker.source.as_ref().and_then(|s| {
                (!checkout.join(s).is_file()).then(|| {
                    format!(
                        "{file}:{}: source={s} is not a file git ls-files lists",
                        b.line
                    )
                })
            });
            dir.into_iter().chain(source)
        })
        .collect();
    let total = Instant::now();
    for (i, (file, block)) in chosen.iter().enumerate() {
        let first = block.script.lines().next().unwrap_or("");
        let head = format!(
            "[{}/{}] {file}:{}: {first}",
            i + 1,
            chosen.len(),
            block.line
        );
        if let (true, Some(why)) = (block.marker.qemu, &missing) {
            say(&format!("{head}\n      skipped: {why}"));
            continue;
        }
        say(&head);
        let started = Instant::now();
        let result = run_block(&tmp.0, file, i, block);
        let took = started.elapsed().as_secs_f64();
        match result {
            Ok(()) => say(&format!("      ok, {took:.1} s")),
            Err(e) => {
                say(&format!("      FAILED after {took:.1} s\n{e}"));
                failures.push(e);
            }
        }
    }
    say(&format!(
        "README commands ({}): {:.1} s in all",
        if long { "long" } else { "short" },
        total.elapsed().as_secs_f64()
    ));
    drop(tmp);
    assert!(
        failures.is_empty(),
        "{} README block(s) failed:\n{}",
        failures.len(),
        failures.join("\n")
    );
}

/// The blocks not marked `long` run as written.
#[test]
fn readme_short_commands_run() {
    run_blocks(false);
}

/// The blocks marked `long` run as written (`.ci/run` runs this with `--ignored`).
#[test]
#[ignore = "the long README blocks: builds, QEMU sessions (.ci/run runs them)"]
fn readme_long_commands_run() {
    run_blocks(true);
}

/// The extraction: languages, markers, console prompts, and the errors a new block without a
/// proper marker or language gets.
#[test]
fn blocks_and_markers_are_read() {
    let md = "\
# Title

```sh
echo root
```

<!-- run: dir=firmware qemu long source=tests/x.sh -->
```bash
cd .. && echo a \\
  b
```

```text
not a command
```

<!-- run: skip=flashes a board (probe-rs) -->
```sh
cargo run --bin board
```

  ~~~console
  $ echo one
  output
  $ echo two \\
  > three
  ~~~

````sh
```
inner fence
````
";
    let blocks = command_blocks(md, "T.md").unwrap();
    let summary: Vec<(usize, &str, &str, Marker)> = blocks
        .iter()
        .map(|b| {
            (
                b.line,
                b.language.as_str(),
                b.script.as_str(),
                b.marker.clone(),
            )
        })
        .collect();
    assert_eq!(
        summary,
        vec![
            (3, "sh", "echo root\n", Marker::default()),
            (
                8,
                "bash",
                "cd .. && echo a \\\n  b\n",
                Marker {
                    dir: "firmware".into(),
                    qemu: true,
                    long: true,
                    source: Some("tests/x.sh".into()),
                    skip: None
                }
            ),
            (
                18,
                "sh",
                "cargo run --bin board\n",
                Marker {
                    skip: Some("flashes a board (probe-rs)".into()),
                    ..Marker::default()
                }
            ),
            (
                22,
                "console",
                "echo one\necho two \\\nthree\n",
                Marker::default()
            ),
            (29, "sh", "```\ninner fence\n", Marker::default()),
        ]
    );

    let errors = [
        ("```\nls\n```\n", "T.md:1: fence without a language"),
        (
            "<!-- run: long -->\n\n```sh\nls\n```\n",
            "T.md:1: marker not right before",
        ),
        (
            "<!-- run: long -->\n```text\nls\n```\n",
            "T.md:1: marker before a `text` block",
        ),
        (
            "<!-- run: fast -->\n```sh\nls\n```\n",
            "T.md:1: unknown marker word `fast`",
        ),
        (
            "<!-- run: skip= -->\n```sh\nls\n```\n",
            "T.md:1: `skip=` needs a reason",
        ),
        (
            "<!-- run: dir=../x -->\n```sh\nls\n```\n",
            "T.md:1: dir=../x must be",
        ),
        ("x\n```sh\nls\n", "T.md:2: block never closed"),
        ("x\n<!-- run: long -->\n", "T.md:2: marker at the end"),
    ];
    for (md, expected) in errors {
        let e = command_blocks(md, "T.md").unwrap_err();
        assert!(e.starts_with(expected), "{md:?}: {e}");
    }
}

/// A failing block is reported with its README, line, command, exit status and output; its
/// background processes are killed and the copy is removed afterwards.
#[test]
fn a_failing_block_is_reported() {
    let tmp =
        TempDir(std::env::temp_dir().join(format!("piezo-readme-fail-{}", std::process::id())));
    std::fs::create_dir_all(tmp.0.join("checkout/sub")).unwrap();
    let pid_file = tmp.0.join("sleeper.pid");
    let block = Block {
        line: 7,
        language: "sh".into(),
        script: format!(
            "sleep 600 &\necho $! > {pids}\ntimeout 600 sleep 600 &\necho $! >> {pids}\n\
             echo to stdout\necho to stderr >&2\nfalse\necho never\n",
            pids = pid_file.display()
        ),
        marker: Marker {
            dir: "sub".into(),
            ..Marker::default()
        },
    };
    let e = run_block(&tmp.0, "X.md", 0, &block).unwrap_err();
    for part in [
        "X.md:7 (run from sub/): exit status: 1",
        "false\necho never\n",
        "stdout\nto stdout",
        "stderr\nto stderr",
    ] {
        assert!(e.contains(part), "{part:?} not in:\n{e}");
    }
    // The background processes, one in the block's group and one (`timeout`) in a group of
    // its own, are gone, or zombies waiting for their new parent to reap them.
    let pids = std::fs::read_to_string(&pid_file).unwrap();
    assert_eq!(pids.lines().count(), 2, "{pids}");
    for pid in pids.lines() {
        let stat = std::fs::read_to_string(Path::new("/proc").join(pid).join("stat"));
        let alive = stat.is_ok_and(|s| {
            !s.rsplit(')')
                .next()
                .unwrap_or("")
                .trim_start()
                .starts_with('Z')
        });
        assert!(!alive, "the block's background process {pid} still runs");
    }
    let ok = Block {
        script: "test \"$(basename \"$PWD\")\" = sub\n".into(),
        ..block
    };
    run_block(&tmp.0, "X.md", 1, &ok).unwrap();
}
