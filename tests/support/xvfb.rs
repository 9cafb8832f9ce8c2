//! A private Xvfb server for the tests that need an X display.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicU32, Ordering};
use std::time::{Duration, Instant};

/// An Xvfb server on a display number nobody uses, stopped on drop.
pub struct Xvfb {
    child: Child,
    /// Its display name (":N").
    pub display: String,
}

impl Xvfb {
    /// Start a server with one `width` × `height` × 24 screen and wait for its socket.
    pub fn start(width: u32, height: u32) -> Xvfb {
        // Spread parallel tests (and other processes' servers) over display numbers.
        static NEXT: AtomicU32 = AtomicU32::new(0);
        let base = 200 + 10 * (std::process::id() % 50);
        for _ in 0..40 {
            let n = base + NEXT.fetch_add(1, Ordering::SeqCst) % 300;
            let socket = PathBuf::from(format!("/tmp/.X11-unix/X{n}"));
            if socket.exists() || Path::new(&format!("/tmp/.X{n}-lock")).exists() {
                continue;
            }
            let mut child = Command::new("Xvfb")
                .arg(format!(":{n}"))
                .args(["-screen", "0", &format!("{width}x{height}x24")])
                .args(["-nolisten", "tcp"])
                .stdout(Stdio::null())
                .stderr(Stdio::null())
                .spawn()
                .expect("Xvfb (Debian package xvfb)");
            let deadline = Instant::now() + Duration::from_secs(20);
            while Instant::now() < deadline {
                if child.try_wait().unwrap().is_some() {
                    break; // Lost the display number to another server: try the next.
                }
                if socket.exists() {
                    return Xvfb {
                        child,
                        display: format!(":{n}"),
                    };
                }
                std::thread::sleep(Duration::from_millis(20));
            }
            let _ = child.kill();
            let _ = child.wait();
        }
        panic!("no free X display number for Xvfb");
    }

    /// The server's process id.
    #[allow(dead_code)] // Not every test file signals the server.
    pub fn pid(&self) -> u32 {
        self.child.id()
    }
}

impl Drop for Xvfb {
    /// SIGTERM, so the server removes its lock file and socket; SIGKILL if it lingers.
    fn drop(&mut self) {
        // SAFETY: signalling our own child, still unreaped.
        unsafe { libc::kill(self.child.id() as libc::pid_t, libc::SIGTERM) };
        let deadline = Instant::now() + Duration::from_secs(5);
        while self.child.try_wait().ok().flatten().is_none() {
            if Instant::now() > deadline {
                let _ = self.child.kill();
                let _ = self.child.wait();
                return;
            }
            std::thread::sleep(Duration::from_millis(10));
        }
    }
}

/// The root window of `display` as 0xRRGGBB pixels, read by `xwd` (XWD: a big-endian header
/// of 25 32-bit fields, the window name, the colour map, then 32-bit ZPixmap rows): width,
/// height and the pixels row by row.
pub fn screenshot(display: &str) -> (u32, u32, Vec<u32>) {
    let out = Command::new("xwd")
        .args(["-root", "-silent", "-display", display])
        .output()
        .expect("xwd (Debian package x11-apps)");
    assert!(out.status.success(), "xwd failed");
    let d = out.stdout;
    let field = |i: usize| u32::from_be_bytes(d[4 * i..4 * i + 4].try_into().unwrap());
    let (header, format, width, height) = (field(0), field(2), field(4), field(5));
    let (little, bpp, stride, ncolors) = (field(7) == 0, field(11), field(12), field(19));
    let masks = [field(14), field(15), field(16)];
    assert_eq!((format, bpp), (2, 32), "ZPixmap, 32 bits per pixel");
    let start = (header + 12 * ncolors) as usize;
    let mut px = Vec::with_capacity((width * height) as usize);
    for y in 0..height as usize {
        for x in 0..width as usize {
            let o = start + y * stride as usize + 4 * x;
            let b: [u8; 4] = d[o..o + 4].try_into().unwrap();
            let p = if little {
                u32::from_le_bytes(b)
            } else {
                u32::from_be_bytes(b)
            };
            let [r, g, b] = masks.map(|m| (p & m) >> m.trailing_zeros());
            px.push((r << 16) | (g << 8) | b);
        }
    }
    (width, height, px)
}
