//! Simulated rigs for tests and benchmarks, built in code instead of written out as TOML in
//! every test file.
//!
//! A test starts from a preset ([`tiny`], [`paper`]) or [`SimRig::new`] and says what
//! differs: `tiny().with("poses.count = 2").edit("p0", |p| p.with("gamma = 1.0"))`. The
//! builder gives the rig file's text ([`SimRig::toml`]) or the parsed [`RigFile`]
//! ([`SimRig::parse`]). A test that checks the rig-file reader itself still writes its TOML
//! by hand.

use super::file::{RigError, RigFile};
use std::fmt::Write;

/// One simulated camera or projector of a [`SimRig`].
#[derive(Clone, Debug, PartialEq)]
pub struct SimDevice {
    /// Device name.
    pub name: String,
    /// Raster width and height (px).
    pub size: (u32, u32),
    /// Pinhole intrinsics fx, fy, cx, cy (px).
    pub intrinsics: [f64; 4],
    /// Lens distortion k1, k2, p1, p2, k3; none: no `sim.distortion` (no distortion).
    pub distortion: Option<[f64; 5]>,
    /// Where the device stands (mm, board frame).
    pub eye: [f64; 3],
    /// The point it looks at (mm, board frame).
    pub target: [f64; 3],
    /// Further `key = value` lines of its table (e.g. `exposure_ms = 10.0`).
    pub lines: Vec<String>,
    /// Its driver when not simulated (e.g. `window`): then its table has no `sim.*` truth.
    pub driver: Option<String>,
}

impl SimDevice {
    /// A device of `size` with intrinsics `[fx, fy, cx, cy]`, 1.5 m in front of the board on
    /// its axis (`eye = [0, 0, 1500]`) and looking at its centre.
    pub fn new(name: &str, size: (u32, u32), intrinsics: [f64; 4]) -> SimDevice {
        SimDevice {
            name: name.into(),
            size,
            intrinsics,
            distortion: None,
            eye: [0.0, 0.0, 1500.0],
            target: [0.0; 3],
            lines: Vec::new(),
            driver: None,
        }
    }

    /// The same device standing at `eye` instead.
    pub fn at(mut self, eye: [f64; 3]) -> SimDevice {
        self.eye = eye;
        self
    }

    /// The same device looking at `target` instead.
    pub fn looking_at(mut self, target: [f64; 3]) -> SimDevice {
        self.target = target;
        self
    }

    /// The same device with lens distortion `[k1, k2, p1, p2, k3]`.
    pub fn distorted(mut self, distortion: [f64; 5]) -> SimDevice {
        self.distortion = Some(distortion);
        self
    }

    /// The same device of raster `size` instead.
    pub fn sized(mut self, size: (u32, u32)) -> SimDevice {
        self.size = size;
        self
    }

    /// The same device with one more `key = value` line in its table (e.g.
    /// `format = "MJPG"`, `trigger_line = 0`), or that line instead of its key's line.
    pub fn with(mut self, line: &str) -> SimDevice {
        set(&mut self.lines, line);
        self
    }

    /// The same device through a real `driver` (e.g. `window`, with a `monitor` line): its
    /// name, raster and lines but no simulated truth.
    pub fn driver(mut self, driver: &str) -> SimDevice {
        self.driver = Some(driver.into());
        self
    }

    /// Its `[[camera]]` or `[[projector]]` table.
    fn table(&self, kind: &str) -> String {
        let driver = self.driver.as_deref().unwrap_or("sim");
        let mut s = format!(
            "[[{kind}]]\nname = \"{}\"\ndriver = \"{driver}\"\nwidth = {}\nheight = {}\n",
            self.name, self.size.0, self.size.1
        );
        for l in &self.lines {
            let _ = writeln!(s, "{l}");
        }
        if self.driver.is_some() {
            return s;
        }
        let [fx, fy, cx, cy] = self.intrinsics;
        let _ = writeln!(
            s,
            "sim.intrinsics = {{ fx = {fx:?}, fy = {fy:?}, cx = {cx:?}, cy = {cy:?} }}"
        );
        if let Some([k1, k2, p1, p2, k3]) = self.distortion {
            let _ = writeln!(
                s,
                "sim.distortion = {{ k1 = {k1:?}, k2 = {k2:?}, p1 = {p1:?}, p2 = {p2:?}, \
                 k3 = {k3:?} }}"
            );
        }
        let (e, t) = (self.eye, self.target);
        let _ = writeln!(
            s,
            "sim.pose = {{ eye = [{:?}, {:?}, {:?}], target = [{:?}, {:?}, {:?}] }}",
            e[0], e[1], e[2], t[0], t[1], t[2]
        );
        s
    }
}

/// `line` (`key = value`) in place of the line of the same key in `lines`, else added.
fn set(lines: &mut Vec<String>, line: &str) {
    let key = |l: &str| l.split('=').next().unwrap_or_default().trim().to_string();
    match lines.iter_mut().find(|l| key(l) == key(line)) {
        Some(old) => *old = line.into(),
        None => lines.push(line.into()),
    }
}

/// A simulated rig file under construction.
#[derive(Clone, Debug, PartialEq)]
pub struct SimRig {
    /// The rig's name.
    pub name: String,
    /// Top-level `key = value` lines after the name (e.g. `board = "hex600"`).
    pub keys: Vec<String>,
    /// Tables before the devices (`timing`, `poses`, `trigger`, …), each its name and its
    /// `key = value` lines.
    pub tables: Vec<(String, Vec<String>)>,
    /// The cameras.
    pub cameras: Vec<SimDevice>,
    /// The projectors.
    pub projectors: Vec<SimDevice>,
    /// TOML text after the devices (`[[positioner]]`, `[[script]]`, …).
    pub tail: String,
}

impl SimRig {
    /// An empty rig called `name`.
    pub fn new(name: &str) -> SimRig {
        SimRig {
            name: name.into(),
            keys: Vec::new(),
            tables: Vec::new(),
            cameras: Vec::new(),
            projectors: Vec::new(),
            tail: String::new(),
        }
    }

    /// The same rig called `name`.
    pub fn named(mut self, name: &str) -> SimRig {
        self.name = name.into();
        self
    }

    /// The same rig with one more table (TOML text, e.g. `"[poses]\ncount = 3"`); its lines
    /// replace those of the same keys if the table is there already.
    pub fn table(mut self, toml: &str) -> SimRig {
        let mut lines = toml.trim().lines();
        let header = lines.next().unwrap_or_default().trim();
        let name = header
            .strip_prefix('[')
            .and_then(|h| h.strip_suffix(']'))
            .unwrap_or_else(|| panic!("a table starts with its [name], not {header:?}"));
        for line in lines.map(str::trim).filter(|l| !l.is_empty()) {
            self = self.with(&format!("{name}.{line}"));
        }
        self
    }

    /// The same rig with one more line: `table.key = value` (e.g. `poses.count = 2`) in that
    /// table, or a top-level `key = value`; either replaces the line of the same key.
    pub fn with(mut self, line: &str) -> SimRig {
        let key = line.split('=').next().unwrap_or_default();
        match key.split_once('.') {
            Some((table, _)) => {
                let line = line[table.len() + 1..].trim();
                let table = table.trim();
                match self.tables.iter_mut().find(|(t, _)| t == table) {
                    Some((_, lines)) => set(lines, line),
                    None => self.tables.push((table.into(), vec![line.into()])),
                }
            }
            None => set(&mut self.keys, line.trim()),
        }
        self
    }

    /// The same rig with one more camera.
    pub fn camera(mut self, device: SimDevice) -> SimRig {
        self.cameras.push(device);
        self
    }

    /// The same rig with one more projector.
    pub fn projector(mut self, device: SimDevice) -> SimRig {
        self.projectors.push(device);
        self
    }

    /// The same rig with the camera or projector `name` changed by `change`.
    ///
    /// # Panics
    /// If the rig has no such device (a mistake in the test that asks).
    pub fn edit(mut self, name: &str, change: impl FnOnce(SimDevice) -> SimDevice) -> SimRig {
        let device = self
            .cameras
            .iter_mut()
            .chain(&mut self.projectors)
            .find(|d| d.name == name)
            .unwrap_or_else(|| panic!("no device {name}"));
        *device = change(device.clone());
        self
    }

    /// The same rig without the cameras and projectors `names`.
    ///
    /// # Panics
    /// If the rig has no device of one of the names.
    pub fn without(mut self, names: &[&str]) -> SimRig {
        for name in names {
            let before = self.cameras.len() + self.projectors.len();
            self.cameras.retain(|d| d.name != *name);
            self.projectors.retain(|d| d.name != *name);
            assert!(
                self.cameras.len() + self.projectors.len() < before,
                "no device {name}"
            );
        }
        self
    }

    /// The same rig with TOML text after its devices (positioners, a script).
    pub fn then(mut self, toml: &str) -> SimRig {
        self.tail += toml;
        self
    }

    /// The rig file's text.
    pub fn toml(&self) -> String {
        let mut s = format!("name = \"{}\"\n", self.name);
        for k in &self.keys {
            let _ = writeln!(s, "{k}");
        }
        for (name, lines) in &self.tables {
            let _ = writeln!(s, "[{name}]");
            for l in lines {
                let _ = writeln!(s, "{l}");
            }
        }
        for c in &self.cameras {
            s += &c.table("camera");
        }
        for p in &self.projectors {
            s += &p.table("projector");
        }
        s + &self.tail
    }

    /// The rig file, parsed (as if read from `NAME.toml`).
    pub fn parse(&self) -> Result<RigFile, RigError> {
        RigFile::parse(&self.toml(), &format!("{}.toml", self.name))
    }

    /// The rig file written to `dir/NAME.toml`; its path.
    ///
    /// # Panics
    /// If the file cannot be written.
    pub fn write(&self, dir: &std::path::Path) -> std::path::PathBuf {
        let path = dir.join(format!("{}.toml", self.name));
        std::fs::write(&path, self.toml()).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        path
    }
}

/// The tiny rig of the capture tests: two 320 × 240 cameras facing each other across the
/// board, two 320 × 200 projectors, three poses, 20 ms frames.
pub fn tiny() -> SimRig {
    let camera = |name, eye| {
        SimDevice::new(name, (320, 240), [1500.0, 1500.0, 159.5, 119.5])
            .at(eye)
            .with("exposure_ms = 10.0")
    };
    let projector =
        |name, eye| SimDevice::new(name, (320, 200), [400.0, 400.0, 160.0, 180.0]).at(eye);
    SimRig::new("tiny")
        .table("[timing]\nframe_period_ms = 20.0")
        .table("[poses]\ncount = 3\nyaw_deg = 20.0\ntilt_deg = 10.0\nshift_mm = 20.0\nseed = 3")
        .camera(camera("front", [0.0, 0.0, 1500.0]))
        .camera(camera("back", [100.0, 0.0, -1500.0]))
        .projector(projector("p0", [300.0, 50.0, 1300.0]))
        .projector(projector("p1", [-300.0, 50.0, -1300.0]))
}

/// A 960 × 600 camera of the reduced paper rig ([`paper`]): focal length `f`, principal
/// point `c`, exposure 10 ms, at `eye`; distortion k1 = `k1`, k2 = 0.05, p1 = 0.0004,
/// p2 = −0.0003.
pub fn paper_camera(name: &str, f: f64, c: [f64; 2], k1: f64, eye: [f64; 3]) -> SimDevice {
    SimDevice::new(name, (960, 600), [f, f, c[0], c[1]])
        .at(eye)
        .distorted([k1, 0.05, 0.0004, -0.0003, 0.0])
        .with("exposure_ms = 10.0")
}

/// The paper rig reduced for the debug build (`sim-small`): three 960 × 600 cameras, two
/// facing the board's front and one its back, and two 1280 × 800 projectors, one lighting
/// each side; seven poses, 20 ms frames.
pub fn paper() -> SimRig {
    // Name, focal length and principal point (px), k1, where it stands (mm).
    #[rustfmt::skip]
    let cameras = [
        ("cam0", 1200.0, [478.0, 301.0], -0.12, [0.0, -311.9, 1467.2]),
        ("cam1", 1220.0, [481.0, 299.0], -0.1, [-860.4, 0.0, 1228.7]),
        ("cam2", 1240.0, [482.0, 300.0], -0.11, [0.0, -311.9, -1467.2]),
    ];
    let projector = |name, f, eye| SimDevice::new(name, (1280, 800), [f, f, 640.0, 740.0]).at(eye);
    let mut rig = SimRig::new("sim-small")
        .with("board = \"hex600\"")
        .table("[timing]\nframe_period_ms = 20.0")
        .table("[poses]\ncount = 7\nyaw_deg = 30.0\ntilt_deg = 20.0\nshift_mm = 40.0\nseed = 5")
        .projector(projector("proj0", 1500.0, [335.2, 113.3, 1250.9]))
        .projector(projector("proj1", 1520.0, [224.9, 113.3, -1275.4]));
    for (name, f, c, k1, eye) in cameras {
        rig = rig.camera(paper_camera(name, f, c, k1, eye));
    }
    rig
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_tiny_rig_reads_as_its_devices_say() {
        let rig = tiny().parse().unwrap();
        assert_eq!((rig.cameras.len(), rig.projectors.len()), (2, 2));
        assert_eq!(rig.poses.as_ref().unwrap().count, 3);
        let text = tiny().toml();
        assert!(
            text.contains("sim.pose = { eye = [100.0, 0.0, -1500.0]"),
            "{text}"
        );
    }

    #[test]
    fn changes_replace_their_keys_and_name_their_devices() {
        let rig = paper()
            .with("poses.count = 2")
            .with("timing.repeats = 4")
            .with("board = \"boards/mine.toml\"")
            .table("[trigger]\nport = \"sim\"")
            .without(&["cam2", "proj1"])
            .edit("cam1", |c| {
                c.with("exposure_ms = 5.0").with("trigger_line = 1")
            })
            .edit("proj0", |p| {
                p.sized((640, 400))
                    .driver("window")
                    .with("monitor = \"screen\"")
            })
            .parse()
            .unwrap();
        assert_eq!(
            (rig.board.as_str(), rig.timing.repeats),
            ("boards/mine.toml", 4)
        );
        assert_eq!(rig.poses.as_ref().unwrap().count, 2);
        let cam1 = &rig.cameras[1];
        assert_eq!((cam1.exposure_ms, cam1.trigger_line), (5.0, Some(1)));
        assert_eq!(rig.cameras[0].sim.unwrap().distortion.k1, -0.12);
        let p = &rig.projectors[0];
        assert_eq!(
            (p.width, p.monitor.as_deref(), p.sim),
            (640, Some("screen"), None)
        );
    }
}
