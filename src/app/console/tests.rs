//! The console's server over real sockets: the page, the state, the event stream, the
//! capture button's rules, and pages that go away.

use super::*;
use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::time::Duration;

/// One HTTP request; gives the status and the body.
fn request(url: &str, method: &str, path: &str) -> (u16, String) {
    let addr = url.trim_start_matches("http://").trim_end_matches('/');
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
    let addr = url.trim_start_matches("http://").trim_end_matches('/');
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    write!(s, "GET /events HTTP/1.1\r\nHost: {addr}\r\n\r\n").unwrap();
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
    let addr = first
        .url()
        .trim_start_matches("http://")
        .trim_end_matches('/');
    let e = Console::start(addr, &[], true).err().unwrap();
    assert!(e.to_string().contains(addr), "{e}");
}

/// One request to `port` on this machine with extra header lines; the whole answer.
fn raw(port: u16, method: &str, path: &str, headers: &str) -> String {
    let mut s = TcpStream::connect(("127.0.0.1", port)).unwrap();
    write!(
        s,
        "{method} {path} HTTP/1.1\r\nHost: x\r\n{headers}Content-Length: 0\r\nConnection: close\r\n\r\n"
    )
    .unwrap();
    let mut all = String::new();
    s.read_to_string(&mut all).unwrap();
    all
}

#[test]
fn a_console_open_to_other_machines_needs_its_token() {
    let console = Console::start("0.0.0.0:0", &[], false).unwrap();
    let url = console.url().to_string();
    let (host, token) = url
        .trim_start_matches("http://")
        .split_once("/?token=")
        .unwrap_or_else(|| panic!("no token in {url}"));
    assert_eq!(token.len(), 32, "{url}");
    let port: u16 = host.rsplit_once(':').unwrap().1.parse().unwrap();
    // Without the token (or with another) the page, the state, the pictures, the events and
    // the button are refused.
    for (method, path) in [
        ("GET", "/"),
        ("GET", "/state"),
        ("GET", "/events"),
        ("GET", "/thumb/0.png"),
        ("POST", "/capture"),
        ("GET", "/?token=00000000000000000000000000000000"),
    ] {
        let answer = raw(port, method, path, "");
        assert!(
            answer.starts_with("HTTP/1.1 403"),
            "{method} {path}: {answer}"
        );
    }
    let wrong = raw(port, "GET", "/state", "Cookie: hexcal_token=abc\r\n");
    assert!(wrong.starts_with("HTTP/1.1 403"), "{wrong}");
    // With it the page comes with the cookie its own requests then carry.
    let page = raw(port, "GET", &format!("/?token={token}"), "");
    assert!(page.starts_with("HTTP/1.1 200"), "{page}");
    assert!(
        page.contains(&format!(
            "hexcal_token={token}; Path=/; HttpOnly; SameSite=Strict"
        )),
        "{page}"
    );
    let cookie = format!("Cookie: other=1; hexcal_token={token}\r\n");
    let state = raw(port, "GET", "/state", &cookie);
    assert!(
        state.starts_with("HTTP/1.1 200") && state.contains("\"status\""),
        "{state}"
    );
    // On loopback no token is asked for (the first test): only this machine reaches it.
    let local = Console::start("127.0.0.1:0", &[], false).unwrap();
    assert!(!local.url().contains("token"), "{}", local.url());
}
