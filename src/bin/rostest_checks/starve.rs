//! A node starved on purpose: a sibling process (a node the same rostest launched) stopped
//! with SIGSTOP for `stop` of every `period` of wall time, then continued, as a host too busy
//! to run it does, only harder and on cue. The simulator's lockstep (`lbr_med_sim`
//! `pose_lockstep_s`, `src/ros/sim_lockstep.rs`) must then slow the simulation rather than
//! hand the controller older poses: the `docking` check's `starve_node`.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Duration;

/// Stops and continues one process until dropped; on drop the process runs on.
pub struct Starver {
    pid: i32,
    done: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
}

impl Starver {
    /// The check's `starve_node` starved (`starve_stop_s` of every `starve_period_s`), or
    /// `None` when it names none.
    pub fn for_params(p: &crate::common::CheckParams) -> Result<Option<Self>, String> {
        if p.starve_node.is_empty() {
            return Ok(None);
        }
        Self::start(&p.starve_node, p.starve_stop_s, p.starve_period_s).map(Some)
    }

    /// Starve the node named `node` (a sibling of this process: its command line holds
    /// `__name:=node`): stopped `stop_s` of every `period_s`, first after `period_s - stop_s`.
    pub fn start(node: &str, stop_s: f64, period_s: f64) -> Result<Self, String> {
        if !(stop_s > 0.0 && period_s > stop_s && period_s.is_finite()) {
            return Err(format!(
                "starve: the stop ({stop_s} s) must be positive and shorter than the period ({period_s} s)"
            ));
        }
        let pid = sibling_pid(node)?;
        let done = Arc::new(AtomicBool::new(false));
        let flag = done.clone();
        let (run, stop) = (
            Duration::from_secs_f64(period_s - stop_s),
            Duration::from_secs_f64(stop_s),
        );
        let thread = std::thread::spawn(move || {
            while !flag.load(Ordering::Acquire) {
                std::thread::sleep(run);
                signal(pid, libc::SIGSTOP);
                std::thread::sleep(stop);
                signal(pid, libc::SIGCONT);
            }
        });
        Ok(Self {
            pid,
            done,
            thread: Some(thread),
        })
    }
}

impl Drop for Starver {
    fn drop(&mut self) {
        self.done.store(true, Ordering::Release);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
        signal(self.pid, libc::SIGCONT);
    }
}

fn signal(pid: i32, sig: libc::c_int) {
    // SAFETY: kill(2) with a pid found among this process's siblings and a stop/continue signal.
    unsafe {
        libc::kill(pid, sig);
    }
}

/// The parent of process `pid` (from `/proc/PID/stat`: the field after the state).
fn parent_of(pid: u32) -> Option<u32> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    let (_, rest) = stat.rsplit_once(')')?;
    rest.split_whitespace().nth(1)?.parse().ok()
}

/// The process with this process's parent whose command line holds `__name:=node`: the
/// node as the same roslaunch started it (another rostest's node of the same name, in a
/// namespace beside this one, has another parent).
fn sibling_pid(node: &str) -> Result<i32, String> {
    let me = std::process::id();
    let parent = parent_of(me).ok_or("starve: cannot read this process's parent")?;
    child_named(parent, node).ok_or_else(|| format!("starve: no node '{node}' started beside this test node"))
}

/// A child of `parent` whose command line holds `__name:=node`.
fn child_named(parent: u32, node: &str) -> Option<i32> {
    let want = format!("__name:={node}");
    std::fs::read_dir("/proc").ok()?.flatten().find_map(|e| {
        let pid = e.file_name().to_str()?.parse::<u32>().ok()?;
        if parent_of(pid) != Some(parent) {
            return None;
        }
        let cmdline = std::fs::read(format!("/proc/{pid}/cmdline")).ok()?;
        let named = cmdline.split(|&b| b == 0).any(|a| a == want.as_bytes());
        named.then(|| i32::try_from(pid).ok()).flatten()
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn state(pid: i32) -> String {
        let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).unwrap_or_default();
        stat.rsplit_once(')')
            .and_then(|(_, r)| r.split_whitespace().next())
            .unwrap_or("")
            .to_string()
    }

    /// `f()` once it is `Some`, polled for up to 5 s (a busy host may take a while to run the
    /// child's exec or to deliver a signal).
    fn within_5_s<T>(mut f: impl FnMut() -> Option<T>) -> Option<T> {
        let start = std::time::Instant::now();
        loop {
            if let Some(v) = f() {
                return Some(v);
            }
            if start.elapsed() > Duration::from_secs(5) {
                return None;
            }
            std::thread::sleep(Duration::from_millis(5));
        }
    }

    #[test]
    fn a_node_is_found_among_its_parents_children_by_name_then_stopped_and_continued() {
        // A shell that stays (two commands: no exec), its $0 the node-name argument.
        let mut child = std::process::Command::new("sh")
            .args(["-c", "sleep 5; true", "__name:=sleeper"])
            .spawn()
            .unwrap();
        let me = std::process::id();
        let pid = within_5_s(|| child_named(me, "sleeper")).expect("the child by its node name");
        assert_eq!(pid as u32, child.id());
        assert_eq!(child_named(me, "sleepe"), None, "the whole name, not a prefix");
        assert_eq!(
            child_named(parent_of(me).unwrap(), "sleeper"),
            None,
            "a child, not a grandchild"
        );
        signal(pid, libc::SIGSTOP);
        assert!(within_5_s(|| (state(pid) == "T").then_some(())).is_some(), "stopped");
        signal(pid, libc::SIGCONT);
        assert!(
            within_5_s(|| (state(pid) != "T").then_some(())).is_some(),
            "running again"
        );
        child.kill().unwrap();
        let _ = child.wait();
        assert!(
            Starver::start("sleeper", 0.3, 0.2).is_err(),
            "a stop longer than its period"
        );
        assert!(sibling_pid("no_such_node").is_err());
    }
}
