//! Frames as cameras deliver them: raw samples of 8 to 16 bits with the camera's counter,
//! timestamp and exposure.

/// Pixels of one camera frame, row-major.
#[derive(Clone, Debug, PartialEq)]
pub enum Pixels {
    /// 8-bit samples.
    Gray8(Vec<u8>),
    /// 16-bit samples (10-, 12- or 16-bit sensors, right-aligned).
    Gray16(Vec<u16>),
}

impl Pixels {
    /// Number of samples.
    pub fn len(&self) -> usize {
        match self {
            Pixels::Gray8(p) => p.len(),
            Pixels::Gray16(p) => p.len(),
        }
    }

    /// Whether there are no samples.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// One frame as a camera delivered it.
#[derive(Clone, Debug, PartialEq)]
pub struct CameraFrame {
    /// Width (px).
    pub width: u32,
    /// Height (px).
    pub height: u32,
    /// Significant bits per sample (8, 10, 12 or 16).
    pub bits: u8,
    /// The samples (width × height of them).
    pub pixels: Pixels,
    /// The camera's own frame counter: one more for every frame it exposed, so a gap means
    /// a dropped frame.
    pub counter: u64,
    /// Timestamp of the exposure (ns, the camera's clock).
    pub timestamp_ns: u64,
    /// Exposure time actually used (µs).
    pub exposure_us: f64,
}
