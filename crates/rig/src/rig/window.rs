//! Projectors as borderless windows on X11 monitors (docs/design.md §11), behind the cargo
//! feature `window`.
//!
//! Takes a projector's rig-file name, a monitor name (as winit reports it: the RandR output,
//! e.g. `HDMI-1`; Xvfb's is `screen`) and the raster size; gives a [`Projector`] whose
//! window covers that monitor exactly: override-redirect at the monitor's position and size,
//! so no window manager moves or decorates it. [`Projector::prepare`] renders one line of
//! each pattern (fringes vary along one axis); [`Projector::show`] returns only when the X
//! server has drawn the slide (a round trip after the present), or fails with
//! [`DeviceError::Gone`] when the window was destroyed, unmapped, or its X connection closed
//! (the client killed by another X client, or the server gone). [`monitors`] lists the
//! monitors for `hexcal devices`; [`bench_show`] times `show`.
//!
//! winit allows one event loop per process and opens the X display (`$DISPLAY`) once, so
//! every window projector of a process is served by one display thread that owns the event
//! loop and lives as long as the process. A lost X connection ends that thread; window
//! projectors cannot be opened again in the same process after it. Surviving a lost
//! connection needs libX11 ≥ 1.7 (`XSetIOErrorExitHandler`); older ones exit the process.

use super::device::{DeviceError, Projector, Slide};
use hexcal_core::pattern::{Direction, Sequence};
use std::collections::HashMap;
use std::num::NonZeroU32;
use std::rc::Rc;
use std::sync::mpsc::{self, RecvTimeoutError, Sender};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::{Duration, Instant};
use winit::application::ApplicationHandler;
use winit::event::WindowEvent;
use winit::event_loop::{ActiveEventLoop, EventLoop, EventLoopProxy};
use winit::platform::x11::{EventLoopBuilderExtX11, WindowAttributesExtX11};
use winit::raw_window_handle::{
    HasDisplayHandle, HasWindowHandle, RawDisplayHandle, RawWindowHandle,
};
use winit::window::{Window, WindowId};
use x11_dl::xlib;

/// How long `show` waits for the display thread to draw a slide.
const SHOW_TIMEOUT: Duration = Duration::from_secs(5);
/// How long opening, listing and closing wait for the display thread.
const REQUEST_TIMEOUT: Duration = Duration::from_secs(10);

/// Xlib request codes whose errors on our own windows are answers, not faults.
const X_GET_WINDOW_ATTRIBUTES: u8 = 3;
const X_GET_GEOMETRY: u8 = 14;

/// A monitor of the X display.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Monitor {
    /// Name (the RandR output name), as a rig file's `monitor`.
    pub name: String,
    /// Width (px).
    pub width: u32,
    /// Height (px).
    pub height: u32,
    /// Left edge on the X screen (px).
    pub x: i32,
    /// Top edge on the X screen (px).
    pub y: i32,
}

impl std::fmt::Display for Monitor {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} ({}×{} at {},{})",
            self.name, self.width, self.height, self.x, self.y
        )
    }
}

/// Why the X display cannot serve windows.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("X display {display}: {reason}")]
pub struct DisplayError {
    /// `$DISPLAY` as the display thread saw it.
    pub display: String,
    /// What went wrong.
    pub reason: String,
}

/// The monitors of the X display (`$DISPLAY`), in winit's order.
pub fn monitors() -> Result<Vec<Monitor>, DisplayError> {
    service()?.ask(Request::Monitors, REQUEST_TIMEOUT)
}

/// What a window shows, as 0x00RRGGBB pixels. A fringe pattern varies along one axis
/// only (docs/design.md §6), so one line of it is kept and repeated.
#[derive(Clone, Debug)]
enum Content {
    /// One grey level everywhere.
    Level(u8),
    /// Column fringes: one row, repeated down the window.
    Columns(Arc<[u32]>),
    /// Row fringes: one pixel per row, repeated along it.
    Rows(Arc<[u32]>),
}

/// 0x00RRGGBB of grey level `g`.
fn grey(g: u8) -> u32 {
    u32::from(g) * 0x0001_0101
}

/// Why a window could not show a slide.
#[derive(Debug)]
enum ShowError {
    /// The window or the X connection is gone.
    Gone(String),
    /// Drawing failed.
    Failed(String),
}

/// What the display thread is asked.
enum Request {
    Monitors(Sender<Vec<Monitor>>),
    Open {
        name: String,
        monitor: String,
        size: (u32, u32),
        reply: Sender<Result<WindowId, DeviceError>>,
    },
    Show {
        window: WindowId,
        content: Content,
        reply: Sender<Result<(), ShowError>>,
    },
    Close {
        window: WindowId,
        reply: Sender<()>,
    },
}

/// The display thread's handle: the event loop's proxy.
struct Service {
    proxy: EventLoopProxy<Request>,
    display: String,
}

/// Why the X connection closed, once it has (set by Xlib's I/O error handler or when the
/// event loop ends).
static LOST: Mutex<Option<String>> = Mutex::new(None);

fn lost() -> Option<String> {
    LOST.lock().unwrap_or_else(|e| e.into_inner()).clone()
}

fn set_lost(reason: &str) {
    LOST.lock()
        .unwrap_or_else(|e| e.into_inner())
        .get_or_insert_with(|| reason.to_string());
}

fn display_name() -> String {
    std::env::var("DISPLAY").unwrap_or_else(|_| "(DISPLAY unset)".into())
}

fn service() -> Result<&'static Service, DisplayError> {
    static SERVICE: OnceLock<Result<Service, DisplayError>> = OnceLock::new();
    SERVICE
        .get_or_init(Service::spawn)
        .as_ref()
        .map_err(Clone::clone)
}

impl Service {
    /// Start the display thread: it builds the event loop and sends back its proxy.
    fn spawn() -> Result<Service, DisplayError> {
        let display = display_name();
        let failed = |reason: String| DisplayError {
            display: display.clone(),
            reason,
        };
        let (tx, rx) = mpsc::channel();
        std::thread::Builder::new()
            .name("x11 display".into())
            .spawn(move || display_thread(tx))
            .map_err(|e| failed(format!("no display thread: {e}")))?;
        match rx.recv_timeout(REQUEST_TIMEOUT) {
            Ok(Ok(proxy)) => Ok(Service {
                proxy,
                display: display.clone(),
            }),
            Ok(Err(reason)) => Err(failed(reason)),
            Err(_) => Err(failed("the display thread did not start".into())),
        }
    }

    /// Send a request made around a reply channel and wait for the answer.
    fn ask<R>(
        &self,
        make: impl FnOnce(Sender<R>) -> Request,
        timeout: Duration,
    ) -> Result<R, DisplayError> {
        let gone = |reason: String| DisplayError {
            display: self.display.clone(),
            reason,
        };
        let ended = || lost().unwrap_or_else(|| "the display thread ended".into());
        let (tx, rx) = mpsc::channel();
        self.proxy.send_event(make(tx)).map_err(|_| gone(ended()))?;
        rx.recv_timeout(timeout).map_err(|e| match e {
            RecvTimeoutError::Timeout => gone(format!("no answer within {timeout:?}")),
            RecvTimeoutError::Disconnected => gone(ended()),
        })
    }
}

/// The display thread: the event loop, until the X connection closes.
fn display_thread(started: Sender<Result<EventLoopProxy<Request>, String>>) {
    let event_loop = match EventLoop::<Request>::with_user_event()
        .with_any_thread(true)
        .build()
    {
        Ok(l) => l,
        Err(e) => {
            let _ = started.send(Err(e.to_string()));
            return;
        }
    };
    let xlib = match xlib::Xlib::open() {
        Ok(x) => x,
        Err(e) => {
            let _ = started.send(Err(format!("libX11: {e}")));
            return;
        }
    };
    let display = match event_loop.display_handle().map(|h| h.as_raw()) {
        Ok(RawDisplayHandle::Xlib(h)) => h.display.map(|d| d.as_ptr().cast::<xlib::Display>()),
        _ => None,
    };
    let Some(display) = display else {
        let _ = started.send(Err("not an Xlib display".into()));
        return;
    };
    // SAFETY: `display` is the event loop's live Xlib display.
    unsafe { survive_connection_loss(&xlib, display) };
    winit::platform::x11::register_xlib_error_hook(Box::new(|_, event| {
        // SAFETY: winit passes the XErrorEvent being reported.
        let e = unsafe { &*event.cast::<xlib::XErrorEvent>() };
        // Our existence checks on a window destroyed behind our back: answered by the
        // call's status, not a fault to log.
        matches!(e.request_code, X_GET_WINDOW_ATTRIBUTES | X_GET_GEOMETRY)
            && matches!(e.error_code, xlib::BadWindow | xlib::BadDrawable)
    }));
    let _ = started.send(Ok(event_loop.create_proxy()));
    let mut app = App {
        xlib,
        display,
        screens: HashMap::new(),
    };
    let end = event_loop.run_app(&mut app);
    set_lost(&match end {
        Ok(()) => "the X connection closed".to_string(),
        Err(e) => format!("the X event loop ended: {e}"),
    });
}

/// Make a closed X connection an error instead of Xlib's default `exit(1)`: the I/O error
/// handler records it, and the exit handler (libX11 ≥ 1.7) returns instead of exiting; Xlib
/// then fails every later call on the display.
///
/// # Safety
/// `display` is a live Xlib display.
unsafe fn survive_connection_loss(x: &xlib::Xlib, display: *mut xlib::Display) {
    unsafe extern "C" fn on_io_error(_: *mut xlib::Display) -> i32 {
        set_lost("the X connection closed (this client was killed by another X client, or the X server went away)");
        0
    }
    unsafe extern "C" fn on_io_exit(_: *mut xlib::Display, _: *mut std::ffi::c_void) {}
    type SetExitHandler = unsafe extern "C" fn(
        *mut xlib::Display,
        unsafe extern "C" fn(*mut xlib::Display, *mut std::ffi::c_void),
        *mut std::ffi::c_void,
    );
    (x.XSetIOErrorHandler)(Some(on_io_error));
    // The library winit loaded; RTLD_NOLOAD finds it without loading another copy.
    let lib = libc::dlopen(c"libX11.so.6".as_ptr(), libc::RTLD_LAZY | libc::RTLD_NOLOAD);
    if lib.is_null() {
        return;
    }
    let sym = libc::dlsym(lib, c"XSetIOErrorExitHandler".as_ptr());
    if !sym.is_null() {
        // SAFETY: the symbol has this signature in libX11 ≥ 1.7 (Xlib.h).
        let set: SetExitHandler = std::mem::transmute::<*mut libc::c_void, SetExitHandler>(sym);
        set(display, on_io_exit, std::ptr::null_mut());
    }
    libc::dlclose(lib);
}

/// One projector window and its drawing surface.
struct Screen {
    window: Rc<Window>,
    xid: xlib::Window,
    surface: softbuffer::Surface<Rc<Window>, Rc<Window>>,
    size: (u32, u32),
    shown: Option<Content>,
    /// Why the window is gone, once it is.
    gone: Option<String>,
}

/// The display thread's state.
struct App {
    xlib: xlib::Xlib,
    display: *mut xlib::Display,
    screens: HashMap<WindowId, Screen>,
}

impl ApplicationHandler<Request> for App {
    fn resumed(&mut self, _: &ActiveEventLoop) {}

    fn user_event(&mut self, event_loop: &ActiveEventLoop, request: Request) {
        match request {
            Request::Monitors(reply) => {
                let _ = reply.send(list(event_loop));
            }
            Request::Open {
                name,
                monitor,
                size,
                reply,
            } => {
                let _ = reply.send(self.open(event_loop, &name, &monitor, size));
            }
            Request::Show {
                window,
                content,
                reply,
            } => {
                let _ = reply.send(self.draw(window, content));
            }
            Request::Close { window, reply } => {
                if self.screens.remove(&window).is_some() && lost().is_none() {
                    // The window is destroyed on drop; wait until the server has done it.
                    // SAFETY: the display is live (no I/O error recorded).
                    unsafe { (self.xlib.XSync)(self.display, xlib::False) };
                }
                let _ = reply.send(());
            }
        }
    }

    fn window_event(&mut self, _: &ActiveEventLoop, id: WindowId, event: WindowEvent) {
        let Some(s) = self.screens.get_mut(&id) else {
            return;
        };
        match event {
            WindowEvent::Destroyed => {
                s.gone
                    .get_or_insert("window destroyed by another X client".into());
            }
            WindowEvent::CloseRequested => {
                s.gone.get_or_insert("window closed by the user".into());
                s.window.set_visible(false);
            }
            WindowEvent::RedrawRequested if s.gone.is_none() => {
                // Exposed (another window moved away): draw the slide again.
                if let Some(c) = s.shown.clone() {
                    let _ = self.draw(id, c);
                }
            }
            _ => {}
        }
    }

    fn about_to_wait(&mut self, event_loop: &ActiveEventLoop) {
        if lost().is_some() {
            event_loop.exit();
        }
    }
}

/// The monitors the event loop sees.
fn list(event_loop: &ActiveEventLoop) -> Vec<Monitor> {
    event_loop
        .available_monitors()
        .map(|m| {
            let (size, pos) = (m.size(), m.position());
            Monitor {
                name: m.name().unwrap_or_default(),
                width: size.width,
                height: size.height,
                x: pos.x,
                y: pos.y,
            }
        })
        .collect()
}

impl App {
    /// A window covering `monitor` for projector `name` of raster `size`.
    fn open(
        &mut self,
        event_loop: &ActiveEventLoop,
        name: &str,
        monitor: &str,
        size: (u32, u32),
    ) -> Result<WindowId, DeviceError> {
        let unsupported = |setting: &str, reason: String| DeviceError::Unsupported {
            device: name.to_string(),
            setting: setting.into(),
            reason,
        };
        let failed = |reason: String| DeviceError::Failed {
            device: name.to_string(),
            reason,
        };
        let all = list(event_loop);
        let Some(m) = all.iter().find(|m| m.name == monitor) else {
            let names: Vec<String> = all.iter().map(Monitor::to_string).collect();
            return Err(unsupported(
                "monitor",
                format!(
                    "no monitor \"{monitor}\" on X display {}; monitors: {}",
                    display_name(),
                    if names.is_empty() {
                        "none".into()
                    } else {
                        names.join(", ")
                    }
                ),
            ));
        };
        if (m.width, m.height) != size {
            return Err(unsupported(
                "width, height",
                format!(
                    "the projector is {}×{} but monitor {} is {}×{}",
                    size.0, size.1, m.name, m.width, m.height
                ),
            ));
        }
        let attributes = Window::default_attributes()
            .with_title(format!("hexcal projector {name}"))
            .with_decorations(false)
            .with_resizable(false)
            .with_position(winit::dpi::PhysicalPosition::new(m.x, m.y))
            .with_inner_size(winit::dpi::PhysicalSize::new(m.width, m.height))
            .with_override_redirect(true);
        let window = Rc::new(
            event_loop
                .create_window(attributes)
                .map_err(|e| failed(format!("window: {e}")))?,
        );
        window.set_cursor_visible(false);
        let xid = match window.window_handle().map(|h| h.as_raw()) {
            Ok(RawWindowHandle::Xlib(h)) => h.window,
            _ => return Err(failed("not an Xlib window".into())),
        };
        let context = softbuffer::Context::new(Rc::clone(&window))
            .map_err(|e| failed(format!("softbuffer: {e}")))?;
        let mut surface = softbuffer::Surface::new(&context, Rc::clone(&window))
            .map_err(|e| failed(format!("softbuffer: {e}")))?;
        let nz = |v: u32| NonZeroU32::new(v).ok_or_else(|| failed("empty raster".into()));
        surface
            .resize(nz(m.width)?, nz(m.height)?)
            .map_err(|e| failed(format!("softbuffer: {e}")))?;
        let id = window.id();
        self.screens.insert(
            id,
            Screen {
                window,
                xid,
                surface,
                size,
                shown: None,
                gone: None,
            },
        );
        // Black until the first slide; also checks the window is mapped where asked.
        self.draw(id, Content::Level(0)).map_err(|e| match e {
            ShowError::Gone(r) | ShowError::Failed(r) => failed(r),
        })?;
        Ok(id)
    }

    /// Draw `content` in window `id`, present it, and wait until the X server has drawn it
    /// (a GetWindowAttributes round trip: the server answers requests in order), checking
    /// the window still exists, is mapped and covers its monitor.
    fn draw(&mut self, id: WindowId, content: Content) -> Result<(), ShowError> {
        let App {
            xlib,
            display,
            screens,
        } = self;
        let s = screens
            .get_mut(&id)
            .ok_or_else(|| ShowError::Gone("window closed".into()))?;
        if let Some(r) = lost().or_else(|| s.gone.clone()) {
            return Err(ShowError::Gone(r));
        }
        // A drawing error on a closed connection (seen first by XCB) is the connection's
        // loss: a round trip through Xlib lets its I/O error handler record it.
        let drawing = |e: softbuffer::SoftBufferError| {
            if lost().is_none() {
                // SAFETY: the display is live or marked failed by Xlib.
                unsafe { (xlib.XSync)(*display, xlib::False) };
            }
            match lost() {
                Some(r) => ShowError::Gone(r),
                None => ShowError::Failed(format!("drawing: {e}")),
            }
        };
        let mut buffer = s.surface.buffer_mut().map_err(drawing)?;
        let width = s.size.0 as usize;
        match &content {
            Content::Level(g) => buffer.fill(grey(*g)),
            Content::Columns(row) => {
                for line in buffer.chunks_exact_mut(width) {
                    line.copy_from_slice(row);
                }
            }
            Content::Rows(column) => {
                for (line, &v) in buffer.chunks_exact_mut(width).zip(column.iter()) {
                    line.fill(v);
                }
            }
        }
        buffer.present().map_err(drawing)?;
        // SAFETY: XWindowAttributes is plain data; Xlib fills it when the call succeeds.
        let mut a: xlib::XWindowAttributes = unsafe { std::mem::zeroed() };
        // SAFETY: the display is live or marked failed by Xlib (then the call returns 0).
        let ok = unsafe { (xlib.XGetWindowAttributes)(*display, s.xid, &mut a) };
        if let Some(r) = lost() {
            return Err(ShowError::Gone(r));
        }
        let gone = if ok == 0 {
            Some("window destroyed by another X client".to_string())
        } else if a.map_state != xlib::IsViewable {
            Some("window unmapped by another X client".to_string())
        } else if (a.width as u32, a.height as u32) != s.size {
            Some(format!(
                "window resized to {}×{} by another X client",
                a.width, a.height
            ))
        } else {
            None
        };
        if let Some(r) = gone {
            s.gone = Some(r.clone());
            return Err(ShowError::Gone(r));
        }
        s.shown = Some(content);
        Ok(())
    }
}

/// A projector driven as a borderless window covering one X11 monitor.
pub struct WindowProjector {
    name: String,
    size: (u32, u32),
    window: WindowId,
    service: &'static Service,
    /// Frame k of the prepared sequence, as the window draws it.
    patterns: Vec<Content>,
    /// The drive level of each intended level (the inverse-gamma table when linearised).
    levels: [u8; 256],
}

impl WindowProjector {
    /// Open projector `name` on `monitor` at raster `width` × `height`, which must be the
    /// monitor's size; the window starts black. Fails naming the projector when the X
    /// display cannot be opened, the monitor does not exist (listing those that do) or
    /// the sizes differ (giving both).
    pub fn open(
        name: &str,
        monitor: &str,
        width: u32,
        height: u32,
    ) -> Result<WindowProjector, DeviceError> {
        let failed = |e: DisplayError| DeviceError::Failed {
            device: name.to_string(),
            reason: e.to_string(),
        };
        let service = service().map_err(failed)?;
        let window = service
            .ask(
                |reply| Request::Open {
                    name: name.to_string(),
                    monitor: monitor.to_string(),
                    size: (width, height),
                    reply,
                },
                REQUEST_TIMEOUT,
            )
            .map_err(failed)??;
        Ok(WindowProjector {
            name: name.to_string(),
            size: (width, height),
            window,
            service,
            patterns: Vec::new(),
            levels: std::array::from_fn(|l| l as u8),
        })
    }
}

impl Projector for WindowProjector {
    fn name(&self) -> &str {
        &self.name
    }

    fn resolution(&self) -> (u32, u32) {
        self.size
    }

    fn prepare(&mut self, sequence: &Sequence, code: usize) -> Result<(), DeviceError> {
        let unsupported = |reason: String| DeviceError::Unsupported {
            device: self.name.clone(),
            setting: "sequence".into(),
            reason,
        };
        let p = sequence.projectors().get(code).ok_or_else(|| {
            unsupported(format!(
                "code {code} of a sequence for {} projectors",
                sequence.projectors().len()
            ))
        })?;
        if (p.width, p.height) != self.size {
            return Err(unsupported(format!(
                "code {code} is {}×{}, the window {}×{}",
                p.width, p.height, self.size.0, self.size.1
            )));
        }
        // The drive levels of `Sequence::pattern_image`, one line per frame.
        let level = |k, u: u32, v: u32| grey(sequence.drive(code, k, f64::from(u), f64::from(v)));
        self.levels = match p.response {
            hexcal_core::pattern::ProjectorResponse::Linearised { gamma } => {
                hexcal_core::pattern::inverse_gamma_lut(gamma)
            }
            _ => std::array::from_fn(|l| l as u8),
        };
        self.patterns = (0..sequence.frame_count())
            .map(|k| match sequence.frame(k).map(|f| f.direction) {
                Some(Direction::Columns) => {
                    Content::Columns((0..p.width).map(|u| level(k, u, 0)).collect())
                }
                _ => Content::Rows((0..p.height).map(|v| level(k, 0, v)).collect()),
            })
            .collect();
        Ok(())
    }

    fn show(&mut self, slide: Slide) -> Result<(), DeviceError> {
        let content = match slide {
            Slide::Black => Content::Level(0),
            Slide::White => Content::Level(255),
            Slide::Level(l) => Content::Level(self.levels[usize::from(l)]),
            Slide::Pattern(k) => self
                .patterns
                .get(k)
                .ok_or_else(|| DeviceError::Unsupported {
                    device: self.name.clone(),
                    setting: "sequence".into(),
                    reason: format!("pattern {k} asked, {} prepared", self.patterns.len()),
                })?
                .clone(),
        };
        let window = self.window;
        let r = self.service.ask(
            |reply| Request::Show {
                window,
                content,
                reply,
            },
            SHOW_TIMEOUT,
        );
        match r {
            Ok(Ok(())) => Ok(()),
            Ok(Err(ShowError::Gone(reason))) => Err(DeviceError::Gone {
                device: self.name.clone(),
                reason,
            }),
            Ok(Err(ShowError::Failed(reason))) => Err(DeviceError::Failed {
                device: self.name.clone(),
                reason,
            }),
            Err(e) => Err(match lost() {
                Some(reason) => DeviceError::Gone {
                    device: self.name.clone(),
                    reason,
                },
                None => DeviceError::Failed {
                    device: self.name.clone(),
                    reason: e.to_string(),
                },
            }),
        }
    }
}

impl Drop for WindowProjector {
    /// Close the window (and wait until the X server has destroyed it).
    fn drop(&mut self) {
        let window = self.window;
        let _ = self
            .service
            .ask(|reply| Request::Close { window, reply }, REQUEST_TIMEOUT);
    }
}

/// Time from `show` called to the slide drawn by the X server.
#[derive(Clone, Debug)]
pub struct ShowBench {
    /// The monitor.
    pub monitor: Monitor,
    /// Patterns rendered by `prepare`, and how long it took.
    pub prepared: (usize, Duration),
    /// Per slide, in order.
    pub times: Vec<Duration>,
}

impl std::fmt::Display for ShowBench {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let mut t = self.times.clone();
        t.sort_unstable();
        let ms = |q: f64| {
            let i = ((t.len() - 1) as f64 * q).round() as usize;
            1e3 * t[i].as_secs_f64()
        };
        write!(
            f,
            "window projector on {}: prepare {} patterns {:.2} ms; {} slides, show → drawn: \
             median {:.2} ms, 90 % {:.2} ms, max {:.2} ms",
            self.monitor,
            self.prepared.0,
            1e3 * self.prepared.1.as_secs_f64(),
            t.len(),
            ms(0.5),
            ms(0.9),
            ms(1.0)
        )
    }
}

/// Show `slides` pattern slides (cycling through a one-projector default sequence at the
/// monitor's size) on `monitor` (the first one when `None`) and time each `show`.
pub fn bench_show(monitor: Option<&str>, slides: usize) -> Result<ShowBench, DeviceError> {
    let failed = |reason: String| DeviceError::Failed {
        device: "bench".into(),
        reason,
    };
    let all = monitors().map_err(|e| failed(e.to_string()))?;
    let m = match monitor {
        Some(name) => all.iter().find(|m| m.name == name),
        None => all.first(),
    }
    .ok_or_else(|| failed(format!("no such monitor; monitors: {all:?}")))?
    .clone();
    let sequence = Sequence::default_for(&[hexcal_core::pattern::ProjectorSetup {
        width: m.width,
        height: m.height,
        response: hexcal_core::pattern::ProjectorResponse::Gamma { gamma: 2.2 },
    }])
    .map_err(|e| failed(e.to_string()))?;
    let mut p = WindowProjector::open("bench", &m.name, m.width, m.height)?;
    let start = Instant::now();
    p.prepare(&sequence, 0)?;
    let prepared = (sequence.frame_count(), start.elapsed());
    let times = (0..slides.max(1))
        .map(|i| {
            let start = Instant::now();
            p.show(Slide::Pattern(i % sequence.frame_count()))?;
            Ok(start.elapsed())
        })
        .collect::<Result<Vec<_>, DeviceError>>()?;
    Ok(ShowBench {
        monitor: m,
        prepared,
        times,
    })
}
