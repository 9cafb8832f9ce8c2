//! The rig self-tests from the command line (issue 31 items 3–4, docs/design.md §11b), on the
//! tiny simulated rig whose projector p0 shows its light 27 ms late: `hexcal check sync`
//! names the lag and the `settle_ms` that makes the sequence safe, and that value makes it
//! pass; a run with `[checks] sync = "on"` refuses to capture on the lagging rig; a capture
//! with `[checks] exposure = "on"` sets each camera to the rig's white level first, records
//! both in the dataset and captures its stacks at that exposure.

#[path = "support/cli.rs"]
mod cli;

use cli::{hexcal, scratch};
use hexcal::app::check::{read_records, SELF_TESTS_FILE};
use hexcal::rig::fixture::{tiny, SimRig};

const LAG_MS: f64 = 27.0;

/// The tiny rig with p0's display `LAG_MS` late and 80 ms frames (room for a settle time).
fn lagging() -> SimRig {
    tiny()
        .with("timing.frame_period_ms = 80.0")
        .edit("p0", |p| {
            p.with(&format!("sim_display = {{ lag_ms = {LAG_MS} }}"))
        })
}

fn text(out: &std::process::Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    )
}

#[test]
fn check_sync_names_the_lag_and_the_settle_time_it_asks_for_makes_it_pass() {
    let dir = scratch("check-sync");
    let rig = lagging().write(&dir);
    let out = hexcal(&["check", "sync", "--rig", rig.to_str().unwrap()]);
    let said = text(&out);
    assert!(!out.status.success(), "{said}");
    assert!(said.contains("front × p0: latency"), "{said}");
    let settle: f64 = said
        .split("set settle_ms = ")
        .nth(1)
        .and_then(|t| t.split_whitespace().next())
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("no settle_ms asked for: {said}"));
    // The light comes LAG_MS late: the settle time asked for covers it, within a wait step
    // of the full test (its waits span run wait + 4 frame periods in 9 steps).
    assert!(
        (LAG_MS..=LAG_MS + 320.0 / 9.0 + 1.0).contains(&settle),
        "{settle}"
    );
    let fixed = lagging()
        .with(&format!("timing.settle_ms = {settle}"))
        .write(&scratch("check-sync-fixed"));
    let json = dir.join("sync.json");
    let out = hexcal(&[
        "check",
        "sync",
        "--rig",
        fixed.to_str().unwrap(),
        "--json",
        json.to_str().unwrap(),
    ]);
    let said = text(&out);
    assert!(out.status.success(), "{said}");
    assert!(said.contains("sync OK"), "{said}");
    assert!(std::fs::read_to_string(&json)
        .unwrap()
        .contains("\"safe_settle_ms\""));
}

#[test]
fn a_run_on_a_lagging_rig_refuses_before_its_first_capture() {
    let dir = scratch("run-sync");
    let rig = lagging().with("checks.sync = \"on\"").write(&dir);
    let data = dir.join("data");
    let out = hexcal(&[
        "run",
        "--rig",
        rig.to_str().unwrap(),
        "--out",
        data.to_str().unwrap(),
        "--held-out",
        "0",
        "--auto",
    ]);
    let said = text(&out);
    assert!(!out.status.success(), "{said}");
    assert!(
        said.contains("sync FAILED") && said.contains("nothing was captured"),
        "{said}"
    );
    let records = read_records(&data.join(SELF_TESTS_FILE)).unwrap();
    assert_eq!(records.len(), 1);
    assert!(!records[0].sync.as_ref().unwrap().passed());
    assert!(!data.join("pose-000").exists(), "a pose was captured");
}

#[test]
fn a_capture_sets_the_exposure_first_and_records_it() {
    let dir = scratch("run-exposure");
    let rig = tiny()
        .with("checks.exposure = \"on\"")
        .with("checks.white_level = 0.5")
        .write(&dir);
    let data = dir.join("data");
    let out = hexcal(&[
        "capture",
        "--rig",
        rig.to_str().unwrap(),
        "--out",
        data.to_str().unwrap(),
        "--poses",
        "1",
    ]);
    let said = text(&out);
    assert!(out.status.success(), "{said}");
    assert!(said.contains("self-tests before pose 0"), "{said}");
    let records = read_records(&data.join(SELF_TESTS_FILE)).unwrap();
    let exposure = records[0].exposure.as_ref().expect("an exposure record");
    assert!(records[0].sync.is_none());
    for c in &exposure.cameras {
        assert!(c.converged && (c.white - 0.5).abs() <= 0.03, "{c:?}");
        // The pose's stack was taken at the exposure the test set.
        let stack = data.join("pose-000").join(&c.camera).join("stack.json");
        let stack = std::fs::read_to_string(&stack).unwrap();
        let set = format!("\"exposure_us\": {}", c.exposure_us);
        assert!(stack.contains(&set), "{set} not in {stack}");
    }
}
