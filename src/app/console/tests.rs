//! The console's server over real sockets: the page, the state, the event stream, the
//! capture button's rules, and pages that go away.

use super::*;
use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::time::Duration;

/// The console's address (host:port) and its token, from its URL.
fn parts(url: &str) -> (&str, &str) {
    let rest = url.trim_start_matches("http://");
    let (addr, query) = rest.split_once("/?token=").unwrap();
    (addr, query)
}

/// One HTTP request carrying the console's token; gives the status and the body.
fn request(url: &str, method: &str, path: &str) -> (u16, String) {
    let token = parts(url).1;
    let sep = if path.contains('?') { '&' } else { '?' };
    raw(url, method, &format!("{path}{sep}token={token}"))
}

/// One HTTP request as given (no token added); gives the status and the body.
fn raw(url: &str, method: &str, path: &str) -> (u16, String) {
    let addr = parts(url).0;
    let mut s = TcpStream::connect(addr).unwrap();
    write!(
        s,
        "{method} {path} HTTP/1.1\r\nHost: {addr}\r\nContent-Length: 0\r\nConnection: close\r\n\r\n"
    )
    .unwrap();
    let mut all = String::new();
    s.read_to_string(&mut all).unwrap();
    let status = all[9..12].parse().unwrap();
    let body = all
        .split_once("\r\n\r\n")
        .map_or("", |(_, b)| b)
        .to_string();
    (status, body)
}

/// An event stream: the connection and its reader.
fn open_stream(url: &str) -> BufReader<TcpStream> {
    let (addr, token) = parts(url);
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    write!(
        s,
        "GET /events?token={token} HTTP/1.1\r\nHost: {addr}\r\n\r\n"
    )
    .unwrap();
    BufReader::new(s)
}

/// The next state sent on a stream.
fn next_state(r: &mut BufReader<TcpStream>) -> serde_json::Value {
    loop {
        let mut line = String::new();
        assert!(r.read_line(&mut line).unwrap() > 0, "stream ended");
        if let Some(json) = line.strip_prefix("data: ") {
            return serde_json::from_str(json).unwrap();
        }
    }
}

#[test]
fn serves_the_page_state_and_events_and_takes_presses_only_when_waiting() {
    let mut console = Console::start("127.0.0.1:0", &[], false).unwrap();
    let url = console.url().to_string();
    assert!(url.starts_with("http://127.0.0.1:"), "{url}");
    // Without the token (or with another) nothing is served and no press is taken.
    let token = parts(&url).1.to_string();
    assert_eq!(token.len(), 32, "{url}");
    let wrong: String = token.chars().rev().collect();
    for path in [
        "/",
        "/state",
        "/events",
        "/thumb/0.png",
        "/index.html?token=",
    ] {
        assert_eq!(raw(&url, "GET", path).0, 403, "{path}");
    }
    assert_eq!(raw(&url, "GET", &format!("/?token={wrong}")).0, 403);
    assert_eq!(raw(&url, "POST", "/capture").0, 403);
    assert_eq!(raw(&url, "POST", "/finish").0, 403);
    let other = Console::start("127.0.0.1:0", &[], false).unwrap();
    assert_ne!(parts(other.url()).1, token, "a fresh token per console");

    let (status, page) = request(&url, "GET", "/");
    assert_eq!(status, 200);
    assert!(page.contains("id=\"sign\"") && page.contains("EventSource"));
    assert!(
        !page.contains("http://") && !page.contains("https://"),
        "no outside address"
    );
    let (status, body) = request(&url, "GET", "/state");
    assert_eq!(status, 200);
    let s: serde_json::Value = serde_json::from_str(&body).unwrap();
    assert_eq!(
        (s["status"].as_str(), s["done"].as_bool()),
        (Some("starting"), Some(false))
    );
    assert_eq!(request(&url, "GET", "/thumb/0.png").0, 404);
    assert_eq!(request(&url, "GET", "/nothing").0, 404);

    // Not waiting for the board: the button is refused and nothing is queued.
    let presses = console.captures();
    assert_eq!(request(&url, "POST", "/capture").0, 409);
    assert!(presses.try_recv().is_err());

    let mut stream = open_stream(&url);
    assert_eq!(next_state(&mut stream)["status"], "starting");
    console.event(&Event::PoseStarted { pose: 0, of: 4 });
    let s = next_state(&mut stream);
    assert_eq!(
        (s["status"].as_str(), s["pose"][0].as_u64()),
        (Some("waiting"), Some(0))
    );
    assert_eq!(request(&url, "POST", "/capture").0, 200);
    presses
        .recv_timeout(Duration::from_secs(5))
        .expect("the press reaches the run");

    // A page that goes away never holds the run up: events keep flowing to the others.
    drop(stream);
    let mut other = open_stream(&url);
    next_state(&mut other);
    for done in 0..200 {
        console.event(&Event::Frames {
            pose: 0,
            done,
            of: 200,
        });
    }
    let mut last = next_state(&mut other);
    while last["frames"][0].as_u64() != Some(199) {
        last = next_state(&mut other);
    }
    assert_eq!(last["status"], "capturing");
}

#[test]
fn the_countdown_is_the_runs_and_capture_waits_it_out() {
    let mut console = Console::start("127.0.0.1:0", &[], false).unwrap();
    let url = console.url().to_string();
    let state = |url: &str| -> serde_json::Value {
        serde_json::from_str(&request(url, "GET", "/state").1).unwrap()
    };
    console.event(&Event::PoseStarted { pose: 2, of: 4 });
    assert_eq!(state(&url)["countdown"], serde_json::Value::Null);
    console.event(&Event::Countdown {
        pose: 2,
        seconds: 3,
    });
    let s = state(&url);
    assert_eq!(
        (s["status"].as_str(), s["countdown"].as_u64()),
        (Some("countdown"), Some(3))
    );
    assert!(
        s["message"].as_str().unwrap().contains("capture in 3 s"),
        "{s}"
    );
    // Counting down, a second press is refused; Finish is taken.
    assert_eq!(request(&url, "POST", "/capture").0, 409);
    assert!(console.captures().try_recv().is_err());
    assert_eq!(request(&url, "POST", "/finish").0, 200);
    // 0: the capture starts; its first frames end the countdown.
    console.event(&Event::Countdown {
        pose: 2,
        seconds: 0,
    });
    let s = state(&url);
    assert_eq!(
        (s["status"].as_str(), s["countdown"].as_u64()),
        (Some("capturing"), Some(0))
    );
    console.event(&Event::Frames {
        pose: 2,
        done: 3,
        of: 30,
    });
    assert_eq!(state(&url)["countdown"], serde_json::Value::Null);
}

#[test]
fn auto_runs_have_no_capture_button() {
    let mut console = Console::start("127.0.0.1:0", &[], true).unwrap();
    console.event(&Event::PoseStarted { pose: 0, of: 4 });
    let url = console.url().to_string();
    assert_eq!(request(&url, "POST", "/capture").0, 409);
    assert!(console.captures().try_recv().is_err());
}

#[test]
fn a_taken_address_is_refused_naming_it() {
    let first = Console::start("127.0.0.1:0", &[], true).unwrap();
    let addr = parts(first.url()).0;
    let e = Console::start(addr, &[], true).err().unwrap();
    assert!(e.to_string().contains(addr), "{e}");
}

#[test]
fn finish_capture_freshness_and_failures_follow_the_run() {
    use crate::app::guide::stats::DeviceStats;
    use crate::observations::{DeviceInfo, DeviceKind};
    let cams = [("cam0".to_string(), [64, 48])];
    let mut console = Console::start("127.0.0.1:0", &cams, false).unwrap();
    let url = console.url().to_string();
    let (presses, finishes) = (console.captures(), console.finishes());
    let state = |url: &str| -> serde_json::Value {
        serde_json::from_str(&request(url, "GET", "/state").1).unwrap()
    };
    // Finish is refused before the run captures.
    assert_eq!(request(&url, "POST", "/finish").0, 409);
    // A preview round, then a new placement: Capture waits for a round taken after it.
    let round = |c: &Console| {
        let view = preview::LiveView {
            png: Vec::new(),
            circles: 0,
            overlay: Overlay::labelled(0, 0, false, &[]),
            count: Default::default(),
            stages: Default::default(),
        };
        c.shared
            .preview(Ok(vec![Some(view)]), std::time::Instant::now());
    };
    round(&console);
    console.event(&Event::PoseStarted { pose: 1, of: 4 });
    assert_eq!(state(&url)["stale"], true);
    let (status, why) = request(&url, "POST", "/capture");
    assert_eq!(status, 409, "{why}");
    assert!(why.contains("not fresh"), "{why}");
    assert!(presses.try_recv().is_err());
    round(&console);
    assert_eq!(state(&url)["stale"], false);
    assert_eq!(request(&url, "POST", "/capture").0, 200);
    assert!(presses.try_recv().is_ok());

    // A refused stack: a failure (the sign cannot read DONE) until the pose is kept.
    console.event(&Event::StackRefused {
        pose: 1,
        camera: "cam0".into(),
        reason: "the white circles clip: lower the exposure".into(),
        attempt: 2,
        of: 3,
    });
    let s = state(&url);
    let failures = s["failures"].as_array().unwrap();
    assert!(
        failures.len() == 1 && failures[0].as_str().unwrap().contains("clip"),
        "{s}"
    );
    let processed = |pose| Event::PoseProcessed {
        pose,
        points: Vec::new(),
        need_views: Vec::new(),
        held_out: false,
    };
    console.event(&processed(1));
    assert_eq!(state(&url)["failures"], serde_json::json!([]));

    // A device that has seen no pose after three calibration poses is a failure.
    let blind = DeviceStats::new(&DeviceInfo {
        name: "proj0".into(),
        kind: DeviceKind::Projector,
        width: 64,
        height: 48,
    });
    let verdicts = console.verdicts();
    let verdict = Verdict {
        devices: vec![blind],
        missing: vec!["proj0: coverage 0 %".into()],
        ..Verdict::default()
    };
    verdicts(&verdict);
    assert_eq!(state(&url)["failures"], serde_json::json!([]));
    console.event(&processed(2));
    console.event(&processed(3));
    verdicts(&verdict);
    let s = state(&url);
    assert!(
        s["failures"][0]
            .as_str()
            .unwrap()
            .starts_with("proj0 has not seen the board in 3 poses"),
        "{s}"
    );

    // Finish before done: taken, with what is not yet met; the run hears it.
    assert_eq!(request(&url, "POST", "/finish").0, 200);
    assert!(finishes.try_recv().is_ok());
    let s = state(&url);
    let said = s["finishing"].as_str().unwrap();
    assert!(
        said.starts_with("Finish before done") && said.contains("proj0: coverage 0 %"),
        "{s}"
    );
    // The calibration leaves a device out: said as a failure naming it and exit 2.
    console.ended(Ok(&["proj0".to_string()]));
    let s = state(&url);
    let last = s["failures"].as_array().unwrap().last().unwrap().clone();
    assert!(
        last.as_str().unwrap().contains("leaves out proj0")
            && last.as_str().unwrap().contains("exit 2"),
        "{s}"
    );
}

/// A request declaring a body larger than the console ever takes (with or without the
/// token: anyone who can reach the port can send it) leaves the server answering; tiny_http
/// would allocate the declared length to drain it (2⁶⁴ − 1 bytes: the server thread died).
#[test]
fn a_huge_declared_body_leaves_the_console_answering() {
    let console = Console::start("127.0.0.1:0", &[], false).unwrap();
    let url = console.url().to_string();
    let (addr, token) = parts(&url);
    for path in ["/state", &format!("/state?token={token}")] {
        let mut s = TcpStream::connect(addr).unwrap();
        write!(
            s,
            "GET {path} HTTP/1.1\r\nHost: {addr}\r\nContent-Length: {}\r\n\r\n",
            u64::MAX
        )
        .unwrap();
        s.set_read_timeout(Some(Duration::from_millis(300)))
            .unwrap();
        let mut answer = String::new();
        let _ = s.read_to_string(&mut answer);
        assert!(answer.is_empty(), "{answer}");
    }
    assert_eq!(request(&url, "GET", "/state").0, 200);
}
