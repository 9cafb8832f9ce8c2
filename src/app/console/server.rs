//! The console's HTTP server (tiny_http, one thread, plus one per open page for its event
//! stream).
//!
//! Routes: `GET /` the page (everything it needs is in it: no CDN, no other file);
//! `GET /state` the state as JSON; `GET /events` server-sent events, one whole state per
//! change (coalesced when they come faster than a page reads); `GET /thumb/C.png` camera C's latest thumbnail; `GET /live/C.png` its latest live
//! preview picture; `POST /capture` the capture
//! button (refused with 409 unless the run waits for the board and the live pictures are
//! fresh); `POST /finish` the Finish button (refused with 409 unless the run captures).
//! Every request must carry the console's access token (`?token=`), else it is refused
//! with 403. A page that goes away
//! only ends its own thread: nothing the server does can block or fail the run.

use super::Shared;
use crossbeam_channel::{bounded, RecvTimeoutError};
use std::io::Write;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Duration;
use tiny_http::{Header, Method, Request, Response, Server};

/// The page, served as it is.
const PAGE: &str = include_str!("page.html");
/// Open event streams at most (each holds a thread).
const MAX_STREAMS: usize = 32;
/// The largest request body the console lets its HTTP server drain (it takes no bodies).
/// tiny_http 0.12 drains a body it was not asked to read by allocating the whole declared
/// `Content-Length` at once when the request is dropped: a request declaring 2⁶⁴ − 1 bytes
/// killed the server thread, one declaring 4 GiB allocated 4 GiB (found by the `console`
/// fuzz target, docs/fuzzing.md).
const MAX_BODY: usize = 64 * 1024;
/// A comment line this often keeps an idle stream open and finds closed pages.
const KEEP_ALIVE: Duration = Duration::from_secs(5);

/// Answer requests until the console closes.
pub(super) fn serve(server: &Server, shared: &Arc<Shared>) {
    for request in server.incoming_requests() {
        if shared.closed.load(Ordering::SeqCst) {
            break;
        }
        if request.body_length().is_some_and(|n| n > MAX_BODY) {
            // Never dropped, so never drained: the client gets no answer, the server a
            // few kilobytes less and one connection thread parked, instead of the
            // allocation of the declared length.
            std::mem::forget(request);
            continue;
        }
        // A page that went away mid-answer harms nothing.
        let _ = respond(request, shared);
    }
}

fn header(name: &str, value: &str) -> Header {
    Header::from_bytes(name.as_bytes(), value.as_bytes()).expect("a valid static header")
}

fn text(status: u16, body: &str) -> Response<std::io::Cursor<Vec<u8>>> {
    Response::from_string(body)
        .with_status_code(status)
        .with_header(header("Content-Type", "text/plain; charset=utf-8"))
}

/// Whether `url`'s query carries `token` (compared in time independent of where it differs).
fn has_token(url: &str, token: &str) -> bool {
    let query = url.split_once('?').map_or("", |(_, q)| q);
    query.split('&').any(|kv| {
        kv.strip_prefix("token=").is_some_and(|t| {
            t.len() == token.len()
                && t.bytes()
                    .zip(token.bytes())
                    .fold(0u8, |d, (a, b)| d | (a ^ b))
                    == 0
        })
    })
}

fn respond(request: Request, shared: &Arc<Shared>) -> std::io::Result<()> {
    if !has_token(request.url(), &shared.token) {
        return request.respond(text(
            403,
            "hexcal console: open the address hexcal printed on its terminal (it carries \
             ?token=…)",
        ));
    }
    let path = request.url().split('?').next().unwrap_or("").to_string();
    let no_store = header("Cache-Control", "no-store");
    match (request.method(), path.as_str()) {
        (Method::Get, "/" | "/index.html") => request.respond(
            Response::from_string(PAGE)
                .with_header(header("Content-Type", "text/html; charset=utf-8"))
                .with_header(no_store),
        ),
        (Method::Get, "/state") => request.respond(
            Response::from_string(shared.snapshot().as_str())
                .with_header(header("Content-Type", "application/json"))
                .with_header(no_store),
        ),
        (Method::Get, "/events") => events(request, shared),
        (Method::Get, p) if p.starts_with("/thumb/") => {
            let png = p
                .strip_prefix("/thumb/")
                .and_then(|c| c.strip_suffix(".png"))
                .and_then(|c| c.parse::<usize>().ok())
                .and_then(|c| shared.thumbnail(c));
            match png {
                Some(png) => request.respond(
                    Response::from_data(png.as_slice())
                        .with_header(header("Content-Type", "image/png"))
                        .with_header(no_store),
                ),
                None => request.respond(text(404, "no thumbnail yet")),
            }
        }
        (Method::Get, p) if p.starts_with("/live/") => {
            let png = p
                .strip_prefix("/live/")
                .and_then(|c| c.strip_suffix(".png"))
                .and_then(|c| c.parse::<usize>().ok())
                .and_then(|c| shared.live_picture(c));
            match png {
                Some(png) => request.respond(
                    Response::from_data(png.as_slice())
                        .with_header(header("Content-Type", "image/png"))
                        .with_header(no_store),
                ),
                None => request.respond(text(404, "no live picture yet")),
            }
        }
        (Method::Post, "/capture") => match shared.press_capture() {
            Ok(()) => request.respond(text(200, "taken")),
            Err(why) => request.respond(text(409, &why.to_string())),
        },
        (Method::Post, "/finish") => match shared.press_finish() {
            Ok(()) => request.respond(text(200, "finishing")),
            Err(why) => request.respond(text(409, &why.to_string())),
        },
        _ => request.respond(text(404, "not found")),
    }
}

/// A page's event stream, in a thread of its own: the current state first, then the newest
/// state after every change (changes that come faster than the page reads are coalesced, so
/// the last one is never lost); it ends when the page goes away or the console closes.
fn events(request: Request, shared: &Arc<Shared>) -> std::io::Result<()> {
    let (tx, rx) = bounded::<()>(1);
    {
        let mut hub = shared.lock_hub();
        if hub.len() >= MAX_STREAMS {
            drop(hub);
            return request.respond(text(503, "too many open pages"));
        }
        hub.push(tx);
    }
    let shared = Arc::clone(shared);
    let spawned = std::thread::Builder::new()
        .name("console page".into())
        .spawn(move || {
            let mut w = request.into_writer();
            let _ = stream(&mut *w, &shared, &rx);
        });
    spawned.map(|_| ())
}

fn stream(
    w: &mut dyn Write,
    shared: &Shared,
    changed: &crossbeam_channel::Receiver<()>,
) -> std::io::Result<()> {
    w.write_all(
        b"HTTP/1.1 200 OK\r\nContent-Type: text/event-stream\r\nCache-Control: no-store\r\n\
          Connection: close\r\n\r\n",
    )?;
    let mut last = shared.snapshot();
    send(w, &last)?;
    loop {
        match changed.recv_timeout(KEEP_ALIVE) {
            Ok(()) => {
                let now = shared.snapshot();
                if !Arc::ptr_eq(&now, &last) {
                    send(w, &now)?;
                    last = now;
                }
            }
            Err(RecvTimeoutError::Timeout) => {
                w.write_all(b": keep-alive\n\n")?;
                w.flush()?;
            }
            Err(RecvTimeoutError::Disconnected) => return Ok(()),
        }
    }
}

/// One event: the state (JSON has no raw newlines, so it fits one `data:` line).
fn send(w: &mut dyn Write, state: &str) -> std::io::Result<()> {
    w.write_all(b"data: ")?;
    w.write_all(state.as_bytes())?;
    w.write_all(b"\n\n")?;
    w.flush()
}
