//! The HTML report as a person sees it: calibrate the paper-like rig (6 cameras,
//! 3 projectors) on 8 board poses, verify on 2 held-out ones, write the page, render it in
//! headless Chromium and check the screenshot shows figures (not a blank or broken page).
//!
//! Needs Chromium at /usr/bin/chromium (Debian package `chromium`).

#[path = "support/cli.rs"]
mod cli;

use cli::scratch;
use hexcal::calib::diagnostics::Diagnosis;
use hexcal::calib::solve::{calibrate, CalibrateOptions};
use hexcal::calib::synthetic::SyntheticRig;
use hexcal::calib::verify::verify;
use hexcal::report::html::{write_html, ReportInput};
use std::collections::HashSet;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

const CHROMIUM: &str = "/usr/bin/chromium";

/// Screenshot `page` into `png` with headless Chromium (no network, a fresh profile).
fn screenshot(page: &Path, png: &Path, profile: &Path) {
    let mut child = Command::new(CHROMIUM)
        .args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-quic",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--hide-scrollbars",
        ])
        .arg(format!("--user-data-dir={}", profile.display()))
        .arg(format!("--screenshot={}", png.display()))
        .arg("--window-size=1400,3000")
        .arg(format!("file://{}", page.display()))
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("start chromium");
    let start = Instant::now();
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            assert!(status.success(), "chromium failed: {status}");
            return;
        }
        if start.elapsed() > Duration::from_secs(180) {
            let _ = child.kill();
            panic!("chromium did not finish within 180 s");
        }
        std::thread::sleep(Duration::from_millis(200));
    }
}

#[test]
fn report_renders_as_a_page_with_figures() {
    assert!(
        Path::new(CHROMIUM).exists(),
        "{CHROMIUM} not found: install the Debian package `chromium` \
         (apt-get install -y chromium; scripts/test.sh lists it)"
    );
    let rig = SyntheticRig::paper(10, 0.1, 11);
    let (train, test): (Vec<_>, Vec<_>) = rig.views().into_iter().partition(|v| v.pose < 8);
    let mut cal = calibrate(
        &rig.board,
        &rig.device_infos(),
        rig.boards.len(),
        &train,
        &CalibrateOptions::default(),
    )
    .unwrap();
    // A few gross outliers (50 px), whose magnified vectors would cross the page.
    for r in cal.solution.residuals.iter_mut().step_by(997) {
        r.error = nalgebra::Vector2::new(50.0, -30.0);
        r.outlier = true;
    }
    let checks = verify(&rig.board, &cal.devices, &test).checks;
    assert!(!checks.is_empty());
    let dir = scratch("report-html");
    let page = dir.join("report.html");
    write_html(
        &ReportInput {
            calibration: &cal,
            verification: &checks,
            title: "Paper rig (simulated)",
            diagnosis: &Diagnosis::of(
                &cal,
                &checks,
                &["poses 8 and 9 held out for verification".into()],
                &Default::default(),
            ),
            self_tests: &[],
        },
        &page,
    )
    .unwrap();
    let html = std::fs::read_to_string(&page).unwrap();
    assert!(html.contains("poses 8 and 9 held out"));
    for d in &cal.devices {
        assert!(html.contains(&d.name));
    }
    plots_are_labelled(&html, cal.devices.len());

    let png = dir.join("report.png");
    screenshot(&page, &png, &dir.join("profile"));
    let shot = image::open(&png).expect("screenshot readable").to_rgb8();
    assert_eq!(shot.dimensions(), (1400, 3000));
    // As a person would look at it: plenty of ink, in many colours, with the device
    // colours (camera blue, projector orange) and dark text near the top.
    let (mut ink, mut colours, mut blue, mut orange, mut dark_top) = (0, HashSet::new(), 0, 0, 0);
    for (_, y, p) in shot.enumerate_pixels() {
        let [r, g, b] = p.0;
        if r < 235 || g < 235 || b < 235 {
            ink += 1;
        }
        colours.insert((r >> 4, g >> 4, b >> 4));
        if b > 150 && r < 80 && g > 90 && g < 150 {
            blue += 1;
        }
        if r > 200 && g > 90 && g < 150 && b < 60 {
            orange += 1;
        }
        if y < 300 && r < 80 && g < 80 && b < 80 {
            dark_top += 1;
        }
    }
    let total = 1400 * 3000;
    assert!(
        ink > total / 20,
        "only {ink} of {total} pixels are not white"
    );
    assert!(
        colours.len() > 40,
        "only {} distinct colours",
        colours.len()
    );
    assert!(
        blue > 200 && orange > 200,
        "device colours: blue {blue}, orange {orange}"
    );
    assert!(
        dark_top > 500,
        "little text at the top: {dark_top} dark pixels"
    );
    eprintln!(
        "report: {} ({} kB), screenshot {}: {:.0} % ink, {} colours",
        page.display(),
        html.len() / 1024,
        png.display(),
        100.0 * ink as f64 / total as f64,
        colours.len()
    );
}

/// The figures' labelling, read from the page's SVG: pixel axes with units on every image
/// figure, each histogram with its device's own σ, the lens-model table, the parameter
/// tables in scrolling boxes, board poses labelled, and every residual vector (outliers
/// included) at most 40 figure px long.
fn plots_are_labelled(html: &str, devices: usize) {
    let count = |s: &str| html.matches(s).count();
    assert_eq!(count(">x (px)</text>"), 2 * devices, "pixel axes");
    assert_eq!(count(">y (px)</text>"), 2 * devices, "pixel axes");
    assert_eq!(count("Rayleigh distribution of this device"), devices);
    assert!(html.contains("id=\"lens-model\""));
    assert!(
        count("<div class=\"scroll\"><table>") >= 3,
        "scrolling tables"
    );
    assert!(
        html.contains("paint-order=\"stroke\""),
        "pose labels on a halo"
    );
    let mut vectors = 0;
    for chunk in html.split("<path d=\"").skip(1) {
        let (d, rest) = chunk.split_once('"').unwrap();
        if !(rest.starts_with(" stroke=\"#9aa3ad\"") || rest.starts_with(" stroke=\"#d62728\"")) {
            continue;
        }
        for seg in d.split('M').filter(|s| !s.is_empty()) {
            let (_, rel) = seg.split_once('l').unwrap();
            let v: Vec<f64> = rel.split(' ').map(|x| x.parse().unwrap()).collect();
            assert!(v[0].hypot(v[1]) <= 40.2, "a vector of {v:?} figure px");
            vectors += 1;
        }
    }
    assert!(vectors > 1000, "{vectors} vectors");
}
