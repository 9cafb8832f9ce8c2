//! The operator console as a person uses it (issue 19): `hexcal run --console` on a small
//! simulated rig, its page open in real headless Chromium driven over the DevTools protocol.
//! Before the first capture it checks the live preview: every camera's live picture
//! arrives and updates with the circles found on it, and the page names the cameras that
//! see the board. The test then clicks the page's Capture button like a mouse would, and checks that every
//! camera's thumbnail appears with the detected circles drawn over it, that the poses-seen
//! counts go up after each capture, that from the third pose on each interim calibration
//! shows a next-pose sentence with the board's target outline drawn in a thumbnail (checked
//! on a screenshot) until the sign turns from NOT DONE to DONE under the rig file's
//! uncertainty threshold, and that a screenshot shows the green sign and the overlays. It
//! then closes the browser and finishes the run with Enter on the terminal: the run must end
//! as it would without a console. Readable at 3 m (issue 34): the next-pose panel at
//! 1920×1080 and on two tablet sizes, and the run's countdown before a capture as the page
//! shows it.
//!
//! Needs Chromium at /usr/bin/chromium (Debian package `chromium`, in scripts/test.sh).

#[path = "support/cli.rs"]
mod cli;

use cli::scratch;
use hexcal::app::console::Console;
use hexcal::app::guide::picture::{Picture, Turn};
use hexcal::app::guide::stats::DeviceStats;
use hexcal::app::guide::verdict::Verdict;
use hexcal::app::guide::{Guidance, Suggestion};
use hexcal::app::progress::Event;
use hexcal::observations::{DeviceInfo, DeviceKind};
use hexcal::rig::fixture::{paper, SimRig};
use serde_json::{json, Value};
use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::path::Path;
use std::process::{Child, ChildStdin, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

const CHROMIUM: &str = "/usr/bin/chromium";

/// The reduced paper rig's two 960×600 cameras facing the board's front and its front
/// projector (30 frames a pose), six poses: small enough for the debug build.
fn console_rig() -> SimRig {
    paper()
        .named("sim-console")
        .with(&format!("guidance.uncertainty_px = {THRESHOLD}"))
        .with("poses.count = 6")
        .without(&["cam2", "proj1"])
}

/// The rig's done threshold on projection uncertainty (px): between what the first interim
/// calibration (3 poses) and the second (4 poses) reach on this rig's fixed schedule (with
/// the lens model chosen by the data and each device's pose in its uncertainty, the
/// projector's worst was 0.207 px after 3 poses and 0.146 after 4), so the page must show
/// one suggestion before the sign turns.
const THRESHOLD: &str = "0.18";

/// How long any one step may take in the debug build on a loaded machine.
const STEP: Duration = Duration::from_secs(240);

/// A child process killed when dropped (a failed test leaves nothing running).
struct Killed(Child);

impl Drop for Killed {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// One GET on 127.0.0.1: the body.
fn get(addr: &str, path: &str) -> String {
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    write!(
        s,
        "GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n"
    )
    .unwrap();
    // Until the server closes (or, if it keeps the connection, goes quiet).
    let mut all = Vec::new();
    let _ = s.read_to_end(&mut all);
    let all = String::from_utf8_lossy(&all);
    all.split_once("\r\n\r\n")
        .map_or("", |(_, b)| b)
        .to_string()
}

/// A DevTools-protocol session with one page.
struct Page {
    ws: tungstenite::WebSocket<tungstenite::stream::MaybeTlsStream<TcpStream>>,
    next: u64,
}

impl Page {
    /// Attach to the first page of the Chromium whose profile is `profile`.
    fn attach(profile: &Path) -> Page {
        let port_file = profile.join("DevToolsActivePort");
        let start = Instant::now();
        let port = loop {
            if let Some(p) = std::fs::read_to_string(&port_file)
                .ok()
                .and_then(|t| t.lines().next().and_then(|l| l.trim().parse::<u16>().ok()))
            {
                break p;
            }
            assert!(
                start.elapsed() < STEP,
                "Chromium did not open its DevTools port"
            );
            std::thread::sleep(Duration::from_millis(100));
        };
        let targets: Value =
            serde_json::from_str(&get(&format!("127.0.0.1:{port}"), "/json/list")).unwrap();
        let url = targets
            .as_array()
            .unwrap()
            .iter()
            .find(|t| t["type"] == "page")
            .expect("a page target")["webSocketDebuggerUrl"]
            .as_str()
            .unwrap()
            .to_string();
        let (ws, _) = tungstenite::connect(url).expect("DevTools WebSocket");
        Page { ws, next: 1 }
    }

    /// Call a DevTools method; gives its result (events in between are skipped).
    fn call(&mut self, method: &str, params: Value) -> Value {
        let id = self.next;
        self.next += 1;
        let msg = json!({"id": id, "method": method, "params": params}).to_string();
        self.ws.send(tungstenite::Message::text(msg)).unwrap();
        loop {
            let m = self.ws.read().unwrap();
            let Ok(text) = m.to_text() else { continue };
            let v: Value = serde_json::from_str(text).unwrap_or(Value::Null);
            if v["id"] == id {
                assert!(v.get("error").is_none(), "{method}: {v}");
                return v["result"].clone();
            }
        }
    }

    /// Evaluate `expr` in the page; gives its value.
    fn eval(&mut self, expr: &str) -> Value {
        let r = self.call(
            "Runtime.evaluate",
            json!({"expression": expr, "returnByValue": true}),
        );
        r["result"]["value"].clone()
    }

    /// What an operator reads off the page.
    fn read(&mut self) -> Value {
        self.eval(
            r#"JSON.stringify({
                sign: document.querySelector('#sign')?.textContent,
                capture: !!document.querySelector('#capture') && !document.querySelector('#capture').disabled,
                finish: document.querySelector('#finish') && !document.querySelector('#finish').disabled ? document.querySelector('#finish').textContent : null,
                failures: [...document.querySelectorAll('#failures li')].map(l => l.textContent),
                cameras: [...document.querySelectorAll('#cameras figure')].map(f => ({
                    name: f.dataset.camera, points: +f.dataset.points, pose: f.dataset.thumbPose,
                    caption: f.querySelector('figcaption').textContent })),
                poses: [...document.querySelectorAll('#devices tbody tr')].map(r => +r.dataset.poses),
                outlines: [...document.querySelectorAll('#cameras figure')].filter(f => f.dataset.outline === '1').map(f => f.dataset.camera),
                uncertainty: [...document.querySelectorAll('#devices tbody tr')].map(r => r.lastChild.textContent),
                live: [...document.querySelectorAll('#cameras figure')].map(f => ({
                    round: f.dataset.liveRound === '' ? -1 : +f.dataset.liveRound,
                    points: +f.dataset.livePoints, sees: f.dataset.sees === '1',
                    caption: f.querySelector('.livecap').textContent })),
                preview: document.querySelector('#live')?.textContent,
                next: document.querySelector('#next')?.textContent,
                message: document.querySelector('#message')?.textContent })"#,
        )
        .as_str()
        .map(|s| serde_json::from_str(s).unwrap())
        .unwrap_or(Value::Null)
    }

    /// Wait until `ok` holds for the text `expr` gives in the page; gives it.
    fn wait_for(&mut self, what: &str, expr: &str, ok: &dyn Fn(&str) -> bool) -> String {
        let start = Instant::now();
        loop {
            let v = self.eval(expr);
            let text = v.as_str().unwrap_or("").to_string();
            if ok(&text) {
                return text;
            }
            assert!(
                start.elapsed() < STEP,
                "waited for {what}; the page shows {text}"
            );
            std::thread::sleep(Duration::from_millis(200));
        }
    }

    /// Wait until `ok` holds for what the page shows; gives it.
    fn wait(&mut self, what: &str, ok: &dyn Fn(&Value) -> bool) -> Value {
        let start = Instant::now();
        loop {
            let v = self.read();
            if ok(&v) {
                return v;
            }
            assert!(
                start.elapsed() < STEP,
                "waited for {what}; the page shows {v}"
            );
            std::thread::sleep(Duration::from_millis(200));
        }
    }

    /// Click the Capture button with the mouse, at its centre.
    fn click_capture(&mut self) {
        self.click("#capture");
    }

    /// Click the element `selector` with the mouse, at its centre (scrolled into view).
    fn click(&mut self, selector: &str) {
        let r = self.eval(&format!(
            "(() => {{ const e = document.querySelector('{selector}'); \
             e.scrollIntoView({{block: 'center'}}); const r = e.getBoundingClientRect(); \
             return [r.x + r.width / 2, r.y + r.height / 2]; }})()"
        ));
        let (x, y) = (r[0].as_f64().unwrap(), r[1].as_f64().unwrap());
        for kind in ["mousePressed", "mouseReleased"] {
            self.call(
                "Input.dispatchMouseEvent",
                json!({"type": kind, "x": x, "y": y, "button": "left", "clickCount": 1}),
            );
        }
    }
}

/// Start `hexcal run --console` with a free port and a countdown of 1 s before each
/// capture; gives the process, its stdin, the console's address and the receiver of its
/// remaining stderr lines.
fn start_run(rig: &Path, out: &Path) -> (Killed, ChildStdin, String, mpsc::Receiver<String>) {
    start_run_at(rig, out, "127.0.0.1:0", "1")
}

/// [`start_run`] with the console on `addr` and a countdown of `countdown` seconds.
fn start_run_at(
    rig: &Path,
    out: &Path,
    addr: &str,
    countdown: &str,
) -> (Killed, ChildStdin, String, mpsc::Receiver<String>) {
    let mut child = Command::new(env!("CARGO_BIN_EXE_hexcal"))
        .args(["run", "--held-out", "1", "--countdown", countdown])
        .args(["--console", addr, "--rig"])
        .arg(rig)
        .arg("--out")
        .arg(out)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let stdin = child.stdin.take().unwrap();
    let stderr = child.stderr.take().unwrap();
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            let _ = tx.send(line);
        }
    });
    let url = loop {
        let line = rx
            .recv_timeout(STEP)
            .expect("the console's address on stderr");
        if let Some(rest) = line.strip_prefix("console: ") {
            break rest.split_whitespace().next().unwrap().to_string();
        }
    };
    (Killed(child), stdin, url, rx)
}

fn start_chromium(profile: &Path) -> Killed {
    let child = Command::new(CHROMIUM)
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
            "--remote-debugging-port=0",
            "--window-size=1400,1000",
        ])
        .arg(format!("--user-data-dir={}", profile.display()))
        .arg("about:blank")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("start chromium");
    Killed(child)
}

/// In the rectangle (x, y, width, height) of the screenshot: pixels of the sign's green, of
/// the overlay's circles (lime, or yellow when not anchored), and of grey (the camera's picture), with the standard
/// deviation of the grey levels (a picture, not a flat fill).
fn count_colours(png: &[u8], [x0, y0, w, h]: [u32; 4]) -> (usize, usize, usize, f64) {
    let shot = image::load_from_memory(png).unwrap().to_rgb8();
    let (mut green, mut lime, mut greys) = (0, 0, Vec::new());
    for y in y0..(y0 + h).min(shot.height()) {
        for x in x0..(x0 + w).min(shot.width()) {
            let [r, g, b] = shot.get_pixel(x, y).0.map(i32::from);
            if (r - 30).abs() < 20 && (g - 142).abs() < 20 && (b - 62).abs() < 20 {
                green += 1;
            }
            // The overlay's circles: lime when anchored, yellow when not.
            if (g > 200 && r < 140 && b < 120) || (r > 220 && g > 190 && b < 60) {
                lime += 1;
            }
            if (r - g).abs() < 8 && (g - b).abs() < 8 {
                greys.push(f64::from(r));
            }
        }
    }
    let n = greys.len().max(1) as f64;
    let mean = greys.iter().sum::<f64>() / n;
    let sd = (greys.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n).sqrt();
    (green, lime, greys.len(), sd)
}

/// Before the first capture, as the operator places the board: every camera's live picture
/// arrives and keeps updating (its round counts up), the circles found on it are drawn
/// over it (checked on a screenshot into `file`), each camera says whether it sees the
/// board, and the page names the cameras that do.
fn check_live_preview(page: &mut Page, file: &Path) {
    let live = |v: &Value| v["live"].as_array().cloned().unwrap_or_default();
    let first = page.wait("live pictures of every camera", &|v| {
        let l = live(v);
        l.len() == 2
            && l.iter().all(|c| c["round"].as_i64().unwrap_or(-1) >= 1)
            && l.iter()
                .any(|c| c["sees"] == true && c["points"].as_u64().unwrap_or(0) > 50)
    });
    let rounds: Vec<i64> = live(&first)
        .iter()
        .map(|c| c["round"].as_i64().unwrap())
        .collect();
    let later = page.wait("the live pictures to update", &|v| {
        live(v)
            .iter()
            .zip(&rounds)
            .all(|(c, r)| c["round"].as_i64().unwrap_or(-1) >= r + 2)
    });
    eprintln!("live preview: {later}");
    let seeing: Vec<String> = live(&later)
        .iter()
        .zip(later["cameras"].as_array().unwrap())
        .filter(|(l, _)| l["sees"] == true)
        .map(|(_, c)| c["name"].as_str().unwrap().to_string())
        .collect();
    let text = later["preview"].as_str().unwrap_or("");
    assert!(text.starts_with("Live preview: "), "{later}");
    assert!(
        !seeing.is_empty() && text.contains(&format!("sees the board now: {}", seeing.join(", "))),
        "{later}"
    );
    for l in live(&later) {
        let caption = l["caption"].as_str().unwrap_or("");
        assert!(caption.starts_with("live, "), "{later}");
        let sees = caption.contains("sees the board: ");
        assert_eq!(sees, l["sees"] == true, "{later}");
    }
    // No pose was captured meanwhile: nothing in the dataset but its description.
    assert!(later["cameras"]
        .as_array()
        .unwrap()
        .iter()
        .all(|c| c["pose"] == ""));
    page.eval(
        "document.querySelector('#cameras figure[data-sees=\"1\"]').scrollIntoView({block: 'center'})",
    );
    let png = screenshot(page, file);
    let r = page.eval(
        "(() => { const f = document.querySelector('#cameras figure[data-sees=\"1\"] canvas'); \
         const r = f.getBoundingClientRect(); return [r.x, r.y, r.width, r.height]; })()",
    );
    let rect: [u32; 4] = std::array::from_fn(|i| r[i].as_f64().unwrap().round() as u32);
    let (_, lime, grey, sd) = count_colours(&png, rect);
    eprintln!(
        "screenshot {}: live picture {lime} px of circles, {grey} px of grey (± {sd:.1})",
        file.display()
    );
    assert!(
        lime > 300,
        "no circles drawn over the live picture: {lime} px"
    );
    assert!(
        grey > (rect[2] * rect[3]) as usize / 10 && sd > 3.0,
        "no live picture: {grey} px of grey, levels ± {sd:.1}"
    );
}

/// Click Capture until the sign reads DONE; after each click, wait for every camera's
/// thumbnail and overlay of that pose and check the poses-seen counts went up; from the
/// third pose on, wait for each interim calibration's guidance (screenshot of the first
/// suggestion into `shots`). Gives the poses captured and the first suggestion shown.
fn capture_until_done(page: &mut Page, shots: &Path) -> (usize, Option<Value>) {
    let mut pose = 0;
    let mut seen_before = 0;
    let mut guided = None;
    loop {
        page.click_capture();
        // After the capture: this pose's thumbnail and overlay in every camera, the
        // button back, and the poses-seen counts up.
        let want = pose.to_string();
        let caption = format!(": pose {pose}:");
        let seen = page.wait(&format!("pose {pose} shown"), &|v| {
            v["capture"] == true
                && v["cameras"].as_array().unwrap().iter().all(|c| {
                    c["pose"] == want.as_str()
                        && c["caption"].as_str().unwrap_or("").contains(&caption)
                })
        });
        let cameras = seen["cameras"].as_array().unwrap();
        assert!(
            cameras
                .iter()
                .any(|c| c["points"].as_u64().unwrap_or(0) > 50),
            "no camera shows the board's circles: {seen}"
        );
        let poses: Vec<u64> = seen["poses"]
            .as_array()
            .unwrap()
            .iter()
            .map(|p| p.as_u64().unwrap())
            .collect();
        assert_eq!(poses.len(), 3, "{seen}");
        assert!(poses.iter().all(|&n| n <= pose as u64 + 1), "{seen}");
        let total: u64 = poses.iter().sum();
        assert!(
            total > seen_before,
            "counts did not go up after pose {pose}: {seen}"
        );
        seen_before = total;
        pose += 1;
        if pose >= 3 {
            // The interim calibration of the poses so far (asked for when the button came
            // back) ends with the sign DONE or a suggestion with its outline.
            let g = page.wait(&format!("guidance after pose {pose}"), &|v| {
                let next = v["next"].as_str().unwrap_or("");
                !next.is_empty() && !next.contains("updating")
            });
            eprintln!("after pose {pose}: {g}");
            if g["sign"] == "DONE" {
                return (pose, guided);
            }
            let next = g["next"].as_str().unwrap();
            assert!(next.starts_with("Next pose: for "), "{g}");
            assert!(next.contains("place the board"), "{g}");
            assert!(!g["outlines"].as_array().unwrap().is_empty(), "{g}");
            if guided.is_none() {
                guided = Some(g);
                check_outline(page, &shots.join("guidance.png"));
                let panel = check_next_pose(page, &shots.join("next-pose.png"));
                assert!(
                    panel["tilt"].as_str().unwrap().starts_with("tilt "),
                    "{panel}"
                );
            }
        }
        assert!(pose < 5, "not done after {pose} poses: {seen}");
    }
}

/// Screenshot the page into `file`; the first camera with a suggested outline must show its
/// orange dashes.
fn check_outline(page: &mut Page, file: &Path) {
    // Below the next-pose panel: scrolled into view.
    page.eval(
        "document.querySelector('#cameras figure[data-outline=\"1\"]').scrollIntoView({block: 'center'})",
    );
    let png = screenshot(page, file);
    let r = page.eval(
        "(() => { const f = document.querySelector('#cameras figure[data-outline=\"1\"] canvas'); \
         const r = f.getBoundingClientRect(); return [r.x, r.y, r.width, r.height]; })()",
    );
    let [x0, y0, w, h]: [u32; 4] = std::array::from_fn(|i| r[i].as_f64().unwrap().round() as u32);
    let shot = image::load_from_memory(&png).unwrap().to_rgb8();
    let mut orange = 0;
    for y in y0..(y0 + h).min(shot.height()) {
        for x in x0..(x0 + w).min(shot.width()) {
            let [r, g, b] = shot.get_pixel(x, y).0.map(i32::from);
            if r > 220 && (g - 145).abs() < 40 && b < 60 {
                orange += 1;
            }
        }
    }
    eprintln!(
        "screenshot {}: {orange} px of the suggested outline",
        file.display()
    );
    assert!(orange > 100, "no outline drawn: {orange} px");
}

/// The least font size (a fraction of the screen's height) of the next-pose panel's line
/// and tilt: about 4 cm on a 80 cm high screen, readable from 3 m.
const READABLE: f64 = 0.05;

/// In the rectangle (x, y, width, height) of the screenshot: pixels of the next pose's
/// outline (orange) and of its turn's arrow (cyan), and the mean position of the arrow's.
fn outline_and_arrow(png: &[u8], [x0, y0, w, h]: [u32; 4]) -> (usize, usize, [f64; 2]) {
    let shot = image::load_from_memory(png).unwrap().to_rgb8();
    let (mut orange, mut cyan, mut at) = (0, 0, [0.0, 0.0]);
    for y in y0..(y0 + h).min(shot.height()) {
        for x in x0..(x0 + w).min(shot.width()) {
            let [r, g, b] = shot.get_pixel(x, y).0.map(i32::from);
            if r > 220 && (110..180).contains(&g) && b < 70 {
                orange += 1;
            }
            // The arrow's #00e5ff, brighter than the lattice's (0, 200, 255, 0.8).
            if r < 60 && g > 215 && b > 240 {
                cyan += 1;
                at = [at[0] + f64::from(x), at[1] + f64::from(y)];
            }
        }
    }
    let n = cyan.max(1) as f64;
    (orange, cyan, [at[0] / n, at[1] / n])
}

/// The next-pose panel as an operator 3 m away sees it (screenshot into `file`): inside the
/// first screen, its line and tilt number at least [`READABLE`] of the screen's height, the
/// suggested outline drawn in thick orange over its camera's picture and, when the run
/// gives a turn, the cyan arrow drawn from the outline's centre where the page says it
/// points. Gives what the panel shows.
fn check_next_pose(page: &mut Page, file: &Path) -> Value {
    page.eval("window.scrollTo(0, 0)");
    let facts = page.eval(
        r#"JSON.stringify((() => {
            const q = (s) => document.querySelector(s);
            const box = (s) => { const r = q(s).getBoundingClientRect(); return [r.x, r.y, r.width, r.height]; };
            const font = (s) => parseFloat(getComputedStyle(q(s)).fontSize);
            const arrow = q('#npcanvas').dataset.arrow;
            return { hidden: q('#nextpose').hidden, screen: [innerWidth, innerHeight],
              camera: q('#nextpose').dataset.camera, line: q('#npline').textContent,
              tilt: q('#nptilt').textContent, turn: q('#npturn').textContent, pose: q('#nppose').textContent,
              fonts: [font('#npline'), font('#nptilt')], boxes: [box('#npcanvas'), box('#npline'), box('#nptilt')],
              arrow: arrow ? JSON.parse(arrow) : null };
        })())"#,
    );
    let facts: Value = serde_json::from_str(facts.as_str().unwrap()).unwrap();
    let png = screenshot(page, file);
    let [w, h] = [0, 1].map(|i| facts["screen"][i].as_f64().unwrap());
    assert_eq!(facts["hidden"], false, "{facts}");
    for font in facts["fonts"].as_array().unwrap() {
        assert!(font.as_f64().unwrap() >= READABLE * h, "{facts}");
    }
    let boxes: Vec<[f64; 4]> = facts["boxes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|b| std::array::from_fn(|i| b[i].as_f64().unwrap()))
        .collect();
    for [x, y, bw, bh] in &boxes {
        let inside = *x >= 0.0 && *y >= 0.0 && x + bw <= w + 0.5 && y + bh <= h + 0.5;
        assert!(
            inside && *bw > 0.0 && *bh > 0.0,
            "not in the first screen: {facts}"
        );
    }
    // The camera's picture is big: a quarter of the screen or more.
    let canvas = boxes[0];
    assert!(canvas[2] * canvas[3] >= w * h / 4.0, "{facts}");
    let rect: [u32; 4] = std::array::from_fn(|i| canvas[i].round() as u32);
    let (orange, cyan, at) = outline_and_arrow(&png, rect);
    eprintln!(
        "screenshot {}: next pose {facts}; {orange} px of outline, {cyan} px of arrow",
        file.display()
    );
    // Thick strokes: as many pixels as five times the picture's width.
    assert!(
        orange as f64 >= 5.0 * canvas[2],
        "outline not drawn big: {orange} px"
    );
    if let Some(a) = facts["arrow"].as_array() {
        let a: Vec<f64> = a.iter().map(|v| v.as_f64().unwrap()).collect();
        let (dx, dy) = (a[2] - a[0], a[3] - a[1]);
        assert!(dx.hypot(dy) >= 0.1 * canvas[2], "arrow too short: {facts}");
        assert!(cyan as f64 >= canvas[2], "no arrow drawn: {cyan} px");
        // Its pixels lie along it, from its start towards its end.
        let (cx, cy) = (at[0] - canvas[0] - a[0], at[1] - canvas[1] - a[1]);
        let along = (cx * dx + cy * dy) / (dx * dx + dy * dy);
        assert!(
            (0.25..1.0).contains(&along),
            "arrow not where it points: {along}"
        );
    }
    facts
}

fn screenshot(page: &mut Page, file: &Path) -> Vec<u8> {
    let shot = page.call("Page.captureScreenshot", json!({"format": "png"}));
    let png = data_encoding::BASE64
        .decode(shot["data"].as_str().unwrap().as_bytes())
        .unwrap();
    std::fs::write(file, &png).unwrap();
    png
}

/// Screenshot the page into `file` and check what it shows: a green sign, circles over
/// the first thumbnail and a grey picture under them.
fn check_screenshot(page: &mut Page, file: &Path) {
    page.eval("window.scrollTo(0, 0)");
    let png = screenshot(page, file);
    let rect = |page: &mut Page, sel: &str| -> [u32; 4] {
        let r = page.eval(&format!(
            "(() => {{ const r = document.querySelector('{sel}').getBoundingClientRect(); \
             return [r.x, r.y, r.width, r.height]; }})()"
        ));
        std::array::from_fn(|i| r[i].as_f64().unwrap().round() as u32)
    };
    let sign = rect(page, "#sign");
    let thumb = rect(page, "#cameras figure canvas");
    let (green, ..) = count_colours(&png, sign);
    let (_, lime, grey, sd) = count_colours(&png, thumb);
    let area = |r: [u32; 4]| (r[2] * r[3]) as usize;
    eprintln!(
        "screenshot {}: sign {green} of {} px green; first thumbnail {lime} px of circles, \
         {grey} px of grey picture (levels ± {sd:.1}) of {} px",
        file.display(),
        area(sign),
        area(thumb)
    );
    assert!(
        green > area(sign) / 2,
        "the DONE sign is not green: {green} px"
    );
    assert!(lime > 300, "no circles drawn over the thumbnail: {lime} px");
    assert!(
        grey > area(thumb) / 10 && sd > 3.0,
        "no camera picture in the thumbnail: {grey} px of grey, levels ± {sd:.1}"
    );
}

/// At 1920×1080 and at a tablet's 1024×768 (screenshots into `dir`): the sign, the message,
/// Capture and Finish lie whole inside the first screen, the sign and the buttons large
/// enough to read from a few metres, and nothing runs off the page's width.
fn check_layout(page: &mut Page, dir: &Path) {
    for [w, h] in [[1920, 1080], [1024, 768]] {
        page.call(
            "Emulation.setDeviceMetricsOverride",
            json!({"width": w, "height": h, "deviceScaleFactor": 1, "mobile": false}),
        );
        let facts = page.eval(
            "JSON.stringify({ wide: document.documentElement.scrollWidth, \
             boxes: ['#sign', '#message', '#capture', '#finish'].map(s => { \
               const r = document.querySelector(s).getBoundingClientRect(); \
               return [r.left, r.top, r.right, r.bottom, \
                 parseFloat(getComputedStyle(document.querySelector(s)).fontSize)]; }) })",
        );
        let facts: Value = serde_json::from_str(facts.as_str().unwrap()).unwrap();
        screenshot(page, &dir.join(format!("console-{w}x{h}.png")));
        eprintln!("layout at {w}×{h}: {facts}");
        assert!(facts["wide"].as_f64().unwrap() <= f64::from(w), "{facts}");
        for (i, b) in facts["boxes"].as_array().unwrap().iter().enumerate() {
            let b: Vec<f64> = b
                .as_array()
                .unwrap()
                .iter()
                .map(|v| v.as_f64().unwrap())
                .collect();
            let inside = b[0] >= 0.0 && b[1] >= 0.0 && b[2] <= f64::from(w) && b[3] <= f64::from(h);
            assert!(
                inside && b[2] > b[0] && b[3] > b[1],
                "element {i} at {w}×{h}: {facts}"
            );
            // The sign and the buttons: letters of at least 28 px (about 2 cm on a tablet).
            if i != 1 {
                assert!(b[4] >= 28.0, "element {i} at {w}×{h}: {facts}");
            }
        }
    }
    page.call("Emulation.clearDeviceMetricsOverride", json!({}));
    // The capture sound is offered, and off unless the operator turns it on.
    let sound = page.eval(
        "(() => { const b = document.querySelector('#sound'); return b ? b.checked : null; })()",
    );
    assert_eq!(sound, json!(false), "the sound toggle, off by default");
}

#[test]
fn console_guides_a_run_in_a_real_browser() {
    assert!(
        Path::new(CHROMIUM).exists(),
        "{CHROMIUM} not found: install the Debian package `chromium` (scripts/test.sh lists it)"
    );
    let dir = scratch("console-browser");
    let rig = dir.join("rig.toml");
    std::fs::write(&rig, console_rig().toml()).unwrap();
    let (mut run, stdin, url, stderr) = start_run(&rig, &dir.join("data"));
    let browser = start_chromium(&dir.join("profile"));
    let mut page = Page::attach(&dir.join("profile"));
    // Without the token printed on the terminal, the page is refused.
    let bare = url.split('?').next().unwrap().to_string();
    page.call("Page.navigate", json!({"url": bare}));
    let refused = page.wait_for(
        "the refusal without the token",
        "document.body ? document.body.textContent : ''",
        &|t| t.contains("token"),
    );
    assert!(
        refused.contains("open the address hexcal printed"),
        "{refused}"
    );
    page.call("Page.navigate", json!({"url": url}));

    let first = page.wait("the capture button", &|v| v["capture"] == true);
    assert_eq!(first["sign"], "NOT DONE", "{first}");
    // Before any interim calibration, the page says where the first poses go.
    let advice = first["next"].as_str().unwrap_or("");
    assert!(
        advice.starts_with("First poses (1 of 3") && advice.contains("every camera shows it"),
        "{first}"
    );
    assert_eq!(first["cameras"].as_array().unwrap().len(), 2, "{first}");
    check_live_preview(&mut page, &dir.join("preview.png"));
    let (pose, guided) = capture_until_done(&mut page, &dir);
    assert!(
        guided.is_some(),
        "done at pose {pose} without a suggestion shown first"
    );
    let done = page.read();
    assert!(
        done["next"].as_str().unwrap_or("").contains("done"),
        "{done}"
    );
    assert_eq!(done["finish"], "Finish", "Finish offered at DONE: {done}");
    assert_eq!(done["failures"], json!([]), "{done}");
    check_screenshot(&mut page, &dir.join("console.png"));
    check_layout(&mut page, &dir);

    // Finish ends the capture and calibrates now; closing the browser then harms nothing.
    page.click("#finish");
    let finishing = page.wait_for(
        "the Finish statement",
        "document.querySelector('#finishing').textContent",
        &|t| !t.is_empty(),
    );
    assert!(
        finishing.starts_with("Finish: the capture ends"),
        "{finishing}"
    );
    drop(page);
    drop(browser);
    let start = Instant::now();
    let status = loop {
        if let Some(s) = run.0.try_wait().unwrap() {
            break s;
        }
        assert!(start.elapsed() < STEP * 2, "the run did not finish");
        std::thread::sleep(Duration::from_millis(200));
    };
    let lines: Vec<String> = stderr.try_iter().collect();
    let mut out = String::new();
    run.0
        .stdout
        .take()
        .unwrap()
        .read_to_string(&mut out)
        .unwrap();
    assert!(status.success(), "{status}: {}\n{out}", lines.join("\n"));
    assert!(
        lines.iter().any(|l| l.starts_with("done: ")),
        "{}",
        lines.join("\n")
    );
    assert!(
        lines.iter().any(|l| l.starts_with("finish: ")),
        "{}",
        lines.join("\n")
    );
    drop(stdin);
    assert!(out.contains("proj0"), "{out}");
}

/// `--guided` on the same rig, without a browser: the simulated board goes where the
/// console's first-pose advice asks for the first three poses, then where the console
/// suggests, and the capture ends as soon as the sign reads DONE, before the schedule's six
/// poses run out; the calibration is written and compared with the truth.
#[test]
fn a_guided_simulated_operator_follows_the_console_until_done() {
    let dir = scratch("console-guided");
    let rig = dir.join("rig.toml");
    std::fs::write(&rig, console_rig().toml()).unwrap();
    let out = dir.join("data");
    let run = Command::new(env!("CARGO_BIN_EXE_hexcal"))
        .args(["run", "--auto", "--guided", "--held-out", "0"])
        .args(["--console", "127.0.0.1:0", "--rig"])
        .arg(&rig)
        .arg("--out")
        .arg(&out)
        .stdin(Stdio::null())
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&run.stderr);
    assert!(run.status.success(), "{}\n{err}", run.status);
    let guided: Vec<&str> = err.lines().filter(|l| l.starts_with("guided: ")).collect();
    eprintln!("{}", guided.join("\n"));
    for k in 0..3 {
        let line = format!("guided: pose {k}: as the first-pose advice asks");
        assert!(guided.iter().any(|l| l.starts_with(&line)), "{err}");
    }
    assert!(
        guided.iter().any(
            |l| l.starts_with("guided: pose 3: where the console suggests: for ")
                || l.starts_with("guided: pose 3: turned to face ")
        ),
        "{err}"
    );
    let done = guided
        .iter()
        .find_map(|l| l.strip_prefix("guided: every device is done after "))
        .and_then(|l| l.split(' ').next())
        .and_then(|n| n.parse::<usize>().ok())
        .unwrap_or_else(|| panic!("never done: {err}"));
    assert!((4..6).contains(&done), "{err}");
    assert!(out.join("calibration/truth.txt").exists(), "{err}");
    assert!(!out.join(format!("pose-{done:03}")).exists(), "{err}");
}

/// A console open to other machines (`--console 0.0.0.0:0`) prints its address with an
/// access token; in a real browser the address without it is refused, with it the page
/// works (its own requests carry the token: the state arrives, the button is live).
#[test]
fn a_console_on_all_addresses_works_only_with_its_token() {
    let dir = scratch("console-token");
    let rig = dir.join("rig.toml");
    std::fs::write(&rig, console_rig().toml()).unwrap();
    let (_run, _stdin, url, _stderr) = start_run_at(&rig, &dir.join("data"), "0.0.0.0:0", "1");
    let (base, token) = url
        .split_once("?token=")
        .expect("a token in the printed address");
    assert_eq!(token.len(), 32, "{url}");
    let base = base.replace("0.0.0.0", "127.0.0.1");
    let _browser = start_chromium(&dir.join("profile"));
    let mut page = Page::attach(&dir.join("profile"));
    page.call("Page.navigate", json!({"url": base}));
    let start = Instant::now();
    loop {
        let body = page.eval("document.body ? document.body.innerText : ''");
        if body
            .as_str()
            .is_some_and(|b| b.starts_with("hexcal console: open the address hexcal printed"))
        {
            break;
        }
        assert!(start.elapsed() < STEP, "not refused: {body}");
        std::thread::sleep(Duration::from_millis(100));
    }
    page.call(
        "Page.navigate",
        json!({"url": format!("{base}?token={token}")}),
    );
    let state = page.wait("the capture button", &|v| v["capture"] == true);
    assert_eq!(state["sign"], "NOT DONE", "{state}");
}

/// What the run's guidance gives the console after an interim calibration: cam1 must see
/// the board in the outline below, turned 25° towards the image's upper right from the last
/// pose, tilted 40° from facing cam1.
fn suggested() -> Verdict {
    let outline = vec![
        [300.0, 150.0],
        [700.0, 120.0],
        [720.0, 460.0],
        [280.0, 430.0],
    ];
    let suggestion = Suggestion {
        target: "cam1".into(),
        predicted: 0.31,
        sentence: "for cam1: place the board in the centre of cam1's view, tilted about 40° \
                   from facing cam1, its right edge nearer to cam1"
            .into(),
        outlines: vec![None, Some(outline)],
        picture: Some(Picture {
            camera: 1,
            tilt_deg: 40.0,
            turn: Some(Turn {
                toward: [0.8, -0.6],
                deg: 25.0,
            }),
            line: "cam1: fill the outline, right edge nearer".into(),
        }),
        pose: nalgebra::Isometry3::identity(),
    };
    // cam1's counts as the run made them: its coverage and steep views, which the page
    // shows as given (its cells, left empty here, would give another coverage).
    let mut cam1 = DeviceStats::new(&DeviceInfo {
        name: "cam1".into(),
        kind: DeviceKind::Camera,
        width: 960,
        height: 600,
    });
    (cam1.poses, cam1.coverage, cam1.steep) = (4, 0.45, 2);
    Verdict {
        threshold: 0.2,
        devices: vec![cam1],
        guidance: Some(Guidance {
            devices: Vec::new(),
            threshold: 0.2,
            done: false,
            suggestion: Some(suggestion),
        }),
        ..Verdict::default()
    }
}

/// The next pose readable at 3 m (issue 34): on a 1920×1080 screen, a 1024×768 tablet and
/// an 800×1280 one upright, the page shows what the run suggests (screenshots into the
/// scratch folder) as the panel [`check_next_pose`] checks: its line and tilt as the run
/// gave them, the arrow pointing where the run's turn points.
#[test]
fn the_next_pose_reads_at_3_m_on_a_screen_and_on_tablets() {
    let dir = scratch("console-next-pose");
    let cams = [
        ("cam0".to_string(), [960, 600]),
        ("cam1".to_string(), [960, 600]),
    ];
    let mut console = Console::start("127.0.0.1:0", &cams, false).unwrap();
    console.event(&Event::PoseStarted { pose: 4, of: 6 });
    (console.verdicts())(&suggested());
    let _browser = start_chromium(&dir.join("profile"));
    let mut page = Page::attach(&dir.join("profile"));
    page.call("Page.navigate", json!({"url": console.url()}));
    for [w, h] in [[1920, 1080], [1024, 768], [800, 1280]] {
        page.call(
            "Emulation.setDeviceMetricsOverride",
            json!({"width": w, "height": h, "deviceScaleFactor": 1, "mobile": false}),
        );
        page.wait_for(
            &format!("the panel drawn at {w}×{h}"),
            "(() => { const c = document.querySelector('#npcanvas'); \
             return c.dataset.screen + ' ' + (c.dataset.arrow || ''); })()",
            &|t| t.starts_with(&format!("{w}x{h} [")),
        );
        let facts = check_next_pose(&mut page, &dir.join(format!("next-pose-{w}x{h}.png")));
        assert_eq!(facts["camera"], "1", "{facts}");
        assert_eq!(facts["line"], "cam1: fill the outline, right edge nearer");
        assert_eq!(facts["tilt"], "tilt 40°");
        assert!(
            facts["turn"].as_str().unwrap().starts_with("turn 25°"),
            "{facts}"
        );
        assert!(
            facts["pose"]
                .as_str()
                .unwrap()
                .starts_with("pose 4 (5 of 6)"),
            "{facts}"
        );
        let a: Vec<f64> = facts["arrow"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_f64().unwrap())
            .collect();
        let (dx, dy) = (a[2] - a[0], a[3] - a[1]);
        let n = dx.hypot(dy);
        assert!(
            (dx / n - 0.8).abs() < 0.01 && (dy / n + 0.6).abs() < 0.01,
            "{facts}"
        );
    }
    // Coverage and steep views: the run's figures.
    let counts = page.eval(
        "(() => { const r = document.querySelector('#devices tr[data-device=\"cam1\"]'); \
         return [r.querySelector('.coverage').textContent, r.querySelector('.steep').textContent]; })()",
    );
    assert_eq!(counts, json!(["45 %", "2"]));
}

/// The countdown is the run's (issue 34): with `--countdown 2`, a press of Capture shows 2,
/// then 1 a second later, then 0 as the run starts the capture (its status turns to
/// capturing with the 0, never before), and the capture's first frames come after it; the
/// terminal says the same seconds in the same order.
#[test]
fn the_countdown_reaches_0_as_the_capture_starts() {
    let dir = scratch("console-countdown");
    let rig = dir.join("rig.toml");
    std::fs::write(&rig, console_rig().toml()).unwrap();
    let (_run, _stdin, url, stderr) = start_run_at(&rig, &dir.join("data"), "127.0.0.1:0", "2");
    let _browser = start_chromium(&dir.join("profile"));
    let mut page = Page::attach(&dir.join("profile"));
    page.call("Page.navigate", json!({"url": url}));
    page.wait("the capture button", &|v| v["capture"] == true);
    // What the page shows, each change with its time: the countdown's number (null while
    // hidden) and the run's status.
    page.eval(
        "window.shown = []; (() => { let last = ''; const log = () => { \
           const on = !document.querySelector('#countdown').hidden; \
           const k = JSON.stringify([on ? document.querySelector('#cdnum').textContent : null, \
             document.body.dataset.status]); \
           if (k !== last) { last = k; window.shown.push([...JSON.parse(k), performance.now()]); } }; \
         new MutationObserver(log).observe(document.body, \
           { subtree: true, childList: true, characterData: true, attributes: true }); log(); })()",
    );
    page.click_capture();
    let shown = page.wait_for(
        "the capture's first frames",
        "JSON.stringify(window.shown)",
        &|t| t.contains(r#"["","capturing""#),
    );
    let shown: Vec<(Value, String, f64)> = serde_json::from_str::<Vec<Value>>(&shown)
        .unwrap()
        .into_iter()
        .map(|e| {
            (
                e[0].clone(),
                e[1].as_str().unwrap().to_string(),
                e[2].as_f64().unwrap(),
            )
        })
        .collect();
    eprintln!("countdown as shown: {shown:?}");
    let numbers: Vec<(&str, &str, f64)> = shown
        .iter()
        .filter_map(|(n, status, t)| {
            Some((n.as_str().filter(|n| !n.is_empty())?, status.as_str(), *t))
        })
        .collect();
    let seq: Vec<(&str, &str)> = numbers.iter().map(|(n, s, _)| (*n, *s)).collect();
    assert_eq!(
        seq,
        [("2", "countdown"), ("1", "countdown"), ("0", "capturing")],
        "{shown:?}"
    );
    for pair in numbers.windows(2) {
        let second = (pair[1].2 - pair[0].2) / 1e3;
        assert!(
            (0.7..1.5).contains(&second),
            "a second lasted {second} s: {shown:?}"
        );
    }
    let zero = numbers[2].2;
    assert!(
        shown.iter().all(|(_, s, t)| s != "capturing" || *t >= zero),
        "capturing before 0: {shown:?}"
    );
    // The terminal: the same seconds, then the capture.
    let mut said = Vec::new();
    while !said.iter().any(|l: &String| l.ends_with("capture starts")) {
        said.push(
            stderr
                .recv_timeout(STEP)
                .expect("the countdown on the terminal"),
        );
    }
    let said: Vec<&String> = said
        .iter()
        .filter(|l| l.starts_with("pose 0: capture"))
        .collect();
    assert_eq!(
        said,
        [
            "pose 0: capture in 2 s: hold the board still",
            "pose 0: capture in 1 s: hold the board still",
            "pose 0: capture starts"
        ],
        "{said:?}"
    );
}
