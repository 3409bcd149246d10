//! A recorded docking played into a live controller in step with the recorded one.
//!
//! A bag plays open loop: its arm follows the recorded controller's commands, not the live
//! ones. The live controller keeps to the recording only if its APPROACH begins when the
//! recorded arm begins to move: later, its tare sees the arm move (`TARE_MOTION`); more than
//! the follow timeout earlier, it leads a still arm (`ARM_NOT_FOLLOWING`). Starting it when
//! the recorded status shows TARE is not enough: the service round trip and the two tares'
//! lengths (each counts the steps' time, which a loaded host stretches) differ by up to
//! 0.1 s. So the bag plays in two parts on its own clock: up to the tare window plus a
//! small lead before the recorded APPROACH, then, with the clock standing still, the live
//! controller is started, then the rest. The live tare then ends `start_lead_s` before the
//! recorded one, whatever the round trip, because no simulated time passes in it.

use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use crate::common::CheckParams;

/// A `rosbag play` process, killed when dropped.
pub struct Player(Child);

impl Drop for Player {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Run `program args` and give its standard output, or why it failed.
fn output(program: &str, args: &[&str]) -> Result<String, String> {
    let out = Command::new(program)
        .args(args)
        .stdin(Stdio::null())
        .output()
        .map_err(|e| format!("{program}: {e}"))?;
    if !out.status.success() {
        return Err(format!(
            "{program} {}: {}: {}",
            args.join(" "),
            out.status,
            String::from_utf8_lossy(&out.stderr).trim()
        ));
    }
    Ok(String::from_utf8_lossy(&out.stdout).into_owned())
}

/// The bag time (s) of the first message of `rostopic echo -p` output `text` (CSV, a header
/// row first) whose `field` column reads `value`.
fn first_time_where(text: &str, field: &str, value: &str) -> Result<f64, String> {
    let mut rows = csv::ReaderBuilder::new().flexible(true).from_reader(text.as_bytes());
    let header = rows.headers().map_err(|e| format!("bad header: {e}"))?.clone();
    if header.is_empty() {
        return Err("no messages".into());
    }
    let col = header
        .iter()
        .position(|h| h == field)
        .ok_or_else(|| format!("no column {field}"))?;
    for row in rows.records() {
        let row = row.map_err(|e| format!("bad row: {e}"))?;
        if row.get(col) == Some(value) {
            let time = row.get(0).unwrap_or_default();
            return time
                .parse::<f64>()
                .map(|ns| ns * 1e-9)
                .map_err(|e| format!("bad time {time:?}: {e}"));
        }
    }
    Err(format!("no message with {field} {value}"))
}

/// The bag's start (s) and when its controller entered APPROACH (s, bag time).
fn recorded_approach(bag: &str, status_topic: &str) -> Result<(f64, f64), String> {
    let start = output("rosbag", &["info", "-y", "-k", "start", bag])?;
    let start: f64 = start
        .trim()
        .parse()
        .map_err(|e| format!("rosbag info {bag}: start {start:?}: {e}"))?;
    let csv = output("rostopic", &["echo", "-b", bag, "-p", status_topic])?;
    let approach =
        first_time_where(&csv, "field.phase", "APPROACH").map_err(|e| format!("{bag} {status_topic}: {e}"))?;
    Ok((start, approach))
}

/// `rosbag play` of `p.bag` with its remaps, after a second for the subscribers to connect,
/// from `from` s into the bag (0: its start) for `duration` s (`None`: to its end).
fn play(p: &CheckParams, from: f64, duration: Option<f64>) -> Result<Player, String> {
    let mut args = vec![
        "play".to_string(),
        "-d".into(),
        "1".into(),
        "-s".into(),
        format!("{from:.6}"),
    ];
    if let Some(d) = duration {
        args.extend(["-u".into(), format!("{d:.6}")]);
    }
    args.push(p.bag.clone());
    args.extend(p.bag_remaps.iter().cloned());
    Command::new("rosbag")
        .args(&args)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .spawn()
        .map(Player)
        .map_err(|e| format!("rosbag {}: {e}", args.join(" ")))
}

/// The live controller's tare window, s (its parameter, as the node loaded it).
fn tare_window(p: &CheckParams) -> Result<f64, String> {
    crate::common::controller_param(p, "tare/window_s")
}

/// Play `p.bag` (module doc): the first part to `start_lead_s` plus the tare window before
/// the recorded APPROACH, then `start` (the live controller's `~start`), then the rest,
/// whose player this returns (keep it until the check ends).
pub fn play_and_start(p: &CheckParams, start: impl FnOnce() -> Result<String, String>) -> Result<Player, String> {
    let (bag_start, approach) = recorded_approach(&p.bag, &p.status_topic)?;
    let cut = approach - tare_window(p)? - p.start_lead_s - bag_start;
    if cut <= 0.0 {
        return Err(format!(
            "{}: the recorded APPROACH {:.3} s into the bag leaves no room for the live tare",
            p.bag,
            approach - bag_start
        ));
    }
    let mut first = play(p, 0.0, Some(cut))?;
    let t0 = Instant::now();
    loop {
        match first.0.try_wait() {
            Ok(Some(s)) if s.success() => break,
            Ok(Some(s)) => return Err(format!("rosbag play {}: {s}", p.bag)),
            Ok(None) if t0.elapsed().as_secs_f64() > p.startup_timeout + cut => {
                return Err(format!("rosbag play {} did not end", p.bag));
            }
            Ok(None) => std::thread::sleep(Duration::from_millis(10)),
            Err(e) => return Err(format!("rosbag play {}: {e}", p.bag)),
        }
    }
    start()?;
    play(p, cut, None)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The first matching row's bag time, in seconds; a missing column or value is named.
    #[test]
    fn the_first_matching_row_gives_the_time() {
        let csv = "%time,field.header.seq,field.phase,field.hold_code\n\
                   1000000000,1,IDLE,NO_TROCAR_POSE\n\
                   1500000000,2,TARE,\n\
                   1900000000,3,APPROACH,\n\
                   2000000000,4,APPROACH,\n";
        assert!((first_time_where(csv, "field.phase", "APPROACH").unwrap() - 1.9).abs() < 1e-12);
        assert!((first_time_where(csv, "field.phase", "TARE").unwrap() - 1.5).abs() < 1e-12);
        assert!(first_time_where(csv, "field.phase", "DONE")
            .unwrap_err()
            .contains("no message"));
        assert!(first_time_where(csv, "field.nope", "DONE")
            .unwrap_err()
            .contains("no column"));
        assert!(first_time_where("", "field.phase", "TARE").is_err());
    }

    /// A quoted field with a comma in it (a string field of the message) is one column.
    #[test]
    fn a_quoted_comma_does_not_shift_the_columns() {
        let csv = "%time,field.reason,field.phase\n\
                   1000000000,\"held, no pose\",TARE\n\
                   1200000000,\"a, b, c\",APPROACH\n";
        assert!((first_time_where(csv, "field.phase", "APPROACH").unwrap() - 1.2).abs() < 1e-12);
    }
}
