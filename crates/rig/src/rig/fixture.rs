//! Simulated rigs for tests and benchmarks, built in code instead of written out as TOML in
//! every test file.
//!
//! Takes the devices (name, raster, pinhole intrinsics, where it stands and looks) and the
//! rig's other tables as TOML text; gives the rig file's text ([`SimRig::toml`]) or the parsed
//! [`RigFile`] ([`SimRig::parse`]). A test that checks the rig-file reader itself still writes
//! its TOML by hand.

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
    /// Where the device stands (mm, board frame).
    pub eye: [f64; 3],
    /// The point it looks at (mm, board frame).
    pub target: [f64; 3],
    /// Further `key = value` lines of its table (e.g. `exposure_ms = 10.0`).
    pub lines: Vec<String>,
}

impl SimDevice {
    /// A device of `size` with intrinsics `[fx, fy, cx, cy]` at `eye` looking at the board's
    /// centre.
    pub fn new(name: &str, size: (u32, u32), intrinsics: [f64; 4], eye: [f64; 3]) -> SimDevice {
        SimDevice {
            name: name.into(),
            size,
            intrinsics,
            eye,
            target: [0.0; 3],
            lines: Vec::new(),
        }
    }

    /// The same device looking at `target` instead.
    pub fn looking_at(mut self, target: [f64; 3]) -> SimDevice {
        self.target = target;
        self
    }

    /// The same device with one more `key = value` line in its table.
    pub fn with(mut self, line: &str) -> SimDevice {
        self.lines.push(line.into());
        self
    }

    /// Its `[[camera]]` or `[[projector]]` table.
    fn table(&self, kind: &str) -> String {
        let [fx, fy, cx, cy] = self.intrinsics;
        let (e, t) = (self.eye, self.target);
        let mut s = format!(
            "[[{kind}]]\nname = \"{}\"\ndriver = \"sim\"\nwidth = {}\nheight = {}\n",
            self.name, self.size.0, self.size.1
        );
        for l in &self.lines {
            let _ = writeln!(s, "{l}");
        }
        let _ = writeln!(
            s,
            "sim.intrinsics = {{ fx = {fx:?}, fy = {fy:?}, cx = {cx:?}, cy = {cy:?} }}\n\
             sim.pose = {{ eye = [{:?}, {:?}, {:?}], target = [{:?}, {:?}, {:?}] }}",
            e[0], e[1], e[2], t[0], t[1], t[2]
        );
        s
    }
}

/// A simulated rig file under construction.
#[derive(Clone, Debug, PartialEq)]
pub struct SimRig {
    /// The rig's name.
    pub name: String,
    /// Tables before the devices (`[timing]`, `[poses]`, `[trigger]`, …), as TOML text.
    pub tables: Vec<String>,
    /// The cameras.
    pub cameras: Vec<SimDevice>,
    /// The projectors.
    pub projectors: Vec<SimDevice>,
}

impl SimRig {
    /// An empty rig called `name`.
    pub fn new(name: &str) -> SimRig {
        SimRig {
            name: name.into(),
            tables: Vec::new(),
            cameras: Vec::new(),
            projectors: Vec::new(),
        }
    }

    /// The same rig with one more table (TOML text, e.g. `"[poses]\ncount = 3"`).
    pub fn table(mut self, toml: &str) -> SimRig {
        self.tables.push(toml.trim_end().into());
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

    /// The named camera, to change it in place.
    ///
    /// # Panics
    /// If the rig has no such camera (a mistake in the test that asks).
    pub fn camera_mut(&mut self, name: &str) -> &mut SimDevice {
        self.cameras
            .iter_mut()
            .find(|c| c.name == name)
            .unwrap_or_else(|| panic!("no camera {name}"))
    }

    /// The rig file's text.
    pub fn toml(&self) -> String {
        let mut s = format!("name = \"{}\"\n", self.name);
        for t in &self.tables {
            let _ = writeln!(s, "{t}");
        }
        for c in &self.cameras {
            s += &c.table("camera");
        }
        for p in &self.projectors {
            s += &p.table("projector");
        }
        s
    }

    /// The rig file, parsed (as if read from `NAME.toml`).
    pub fn parse(&self) -> Result<RigFile, RigError> {
        RigFile::parse(&self.toml(), &format!("{}.toml", self.name))
    }
}

/// The tiny rig of the capture tests: two 320 × 240 cameras facing each other across the
/// board, two 320 × 200 projectors, three poses, 20 ms frames.
pub fn tiny() -> SimRig {
    let camera = |name, eye| {
        SimDevice::new(name, (320, 240), [1500.0, 1500.0, 159.5, 119.5], eye)
            .with("exposure_ms = 10.0")
    };
    let projector = |name, eye| SimDevice::new(name, (320, 200), [400.0, 400.0, 160.0, 180.0], eye);
    SimRig::new("tiny")
        .table("[timing]\nframe_period_ms = 20.0")
        .table("[poses]\ncount = 3\nyaw_deg = 20.0\ntilt_deg = 10.0\nshift_mm = 20.0\nseed = 3")
        .camera(camera("front", [0.0, 0.0, 1500.0]))
        .camera(camera("back", [100.0, 0.0, -1500.0]))
        .projector(projector("p0", [300.0, 50.0, 1300.0]))
        .projector(projector("p1", [-300.0, 50.0, -1300.0]))
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
}
