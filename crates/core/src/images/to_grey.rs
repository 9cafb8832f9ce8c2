//! Camera pixel formats to grey (docs/design.md §11 "Colour, packed and compressed formats").
//!
//! Takes one buffer as a camera sends it — 8- or 16-bit samples, PFNC `…p` bit streams,
//! GigE Vision `…Packed` pairs, a Bayer mosaic, RGB / BGR, YUYV, a JPEG — with its
//! [`SampleFormat`], and gives the grey [`Pixels`] every stage reads. The conversions, chosen
//! by measurement (§11):
//!
//! - **Packed** samples are unpacked, nothing else.
//! - **Bayer** mosaics stay at full resolution with no interpolation: each sample is
//!   multiplied by its colour's gain ([`balance_mosaic`]), so a neutral board (black print on
//!   white) under white light gives the same value through every filter. The gains come
//!   from the scene itself ([`grey_world_gains`]: over the bright 2×2 cells, the ratio of
//!   green's sum to each channel's) and [`BayerBalance`] holds them for a whole acquisition, so every frame
//!   of a phase-shift stack sees the same per-pixel scale (a phase does not depend on it).
//! - **RGB / BGR** (demosaiced by the camera) give their BT.601 luma.
//! - **JPEG** (MJPEG) gives its luma plane as coded (Y of YCbCr, or the one plane of a grey
//!   JPEG): no chroma is upsampled or mixed in.

use super::Pixels;

/// A colour filter array's phase: the colours of the top-left 2×2 cell, row by row.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Cfa {
    /// Red, green / green, blue.
    Rggb,
    /// Green, red / blue, green.
    Grbg,
    /// Green, blue / red, green.
    Gbrg,
    /// Blue, green / green, red.
    Bggr,
}

impl Cfa {
    /// The four phases.
    pub const ALL: [Cfa; 4] = [Cfa::Rggb, Cfa::Grbg, Cfa::Gbrg, Cfa::Bggr];

    /// Colour channel (0 red, 1 green, 2 blue) of pixel (x, y).
    pub fn channel(self, x: usize, y: usize) -> usize {
        let cell = match self {
            Cfa::Rggb => [0, 1, 1, 2],
            Cfa::Grbg => [1, 0, 2, 1],
            Cfa::Gbrg => [1, 2, 0, 1],
            Cfa::Bggr => [2, 1, 1, 0],
        };
        cell[(y & 1) * 2 + (x & 1)]
    }
}

/// How samples lie in a buffer's bytes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Packing {
    /// One byte per sample.
    U8,
    /// One little-endian 16-bit word per sample, right-aligned.
    U16Le,
    /// PFNC `…p` (Mono10p, Mono12p, BayerRG12p, …): a little-endian bit stream, `bits` per
    /// sample, least significant bit first; each row starts on a byte.
    LsbStream,
    /// GigE Vision `…Packed` (Mono10Packed, Mono12Packed, …): two samples in three bytes —
    /// byte 0 the first sample's high 8 bits, byte 2 the second's, byte 1 their low bits
    /// (the first's from bit 0, the second's from bit 4).
    GvspPair,
}

/// What a buffer's samples are.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Colour {
    /// Monochrome.
    Mono,
    /// YUV 4:2:2 interleaved (Y0 U Y1 V): its luma.
    YuyvLuma,
    /// A raw Bayer mosaic.
    Bayer(Cfa),
    /// Red, green, blue bytes per pixel.
    Rgb,
    /// Blue, green, red bytes per pixel.
    Bgr,
    /// A JPEG image (one MJPEG frame).
    Jpeg,
}

/// A camera pixel format: what the samples are, how they are packed and how many bits each
/// carries.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct SampleFormat {
    /// What the samples are.
    pub colour: Colour,
    /// How they lie in the bytes.
    pub packing: Packing,
    /// Significant bits per sample (8 to 16).
    pub bits: u8,
}

impl SampleFormat {
    /// Monochrome, `bits` per sample, packed as `packing`.
    pub const fn mono(packing: Packing, bits: u8) -> Self {
        SampleFormat {
            colour: Colour::Mono,
            packing,
            bits,
        }
    }

    /// A Bayer mosaic of phase `cfa`, `bits` per sample, packed as `packing`.
    pub const fn bayer(cfa: Cfa, packing: Packing, bits: u8) -> Self {
        SampleFormat {
            colour: Colour::Bayer(cfa),
            packing,
            bits,
        }
    }

    /// An 8-bit format of one byte per sample (`colour` RGB, BGR, YUYV or JPEG).
    pub const fn bytes(colour: Colour) -> Self {
        SampleFormat {
            colour,
            packing: Packing::U8,
            bits: 8,
        }
    }

    /// Bytes per row of `width` pixels with no padding (the minimum stride); `None` for a
    /// width the packing cannot hold (odd for pairs) and for JPEG (no fixed size).
    pub fn row_bytes(&self, width: usize) -> Option<usize> {
        let samples = match self.colour {
            Colour::Jpeg => return None,
            Colour::Rgb | Colour::Bgr => 3 * width,
            Colour::YuyvLuma => 2 * width,
            Colour::Mono | Colour::Bayer(_) => width,
        };
        match self.packing {
            Packing::U8 => Some(samples),
            Packing::U16Le => Some(2 * samples),
            Packing::LsbStream => Some((samples * usize::from(self.bits)).div_ceil(8)),
            Packing::GvspPair => (samples % 2 == 0).then_some(samples / 2 * 3),
        }
    }

    /// Preference when the rig file names no format (lower first): monochrome, then YUYV
    /// luma, then Bayer, then RGB / BGR, then JPEG; within a class the rig file's `bits`
    /// exactly before a wider container. `None` when the format cannot give `bits`.
    pub fn rank(&self, bits: u8) -> Option<(u8, u8)> {
        let class = match self.colour {
            Colour::Mono => 0,
            Colour::YuyvLuma => 1,
            Colour::Bayer(_) => 2,
            Colour::Rgb | Colour::Bgr => 3,
            Colour::Jpeg => 4,
        };
        let fit = match (self.bits, bits) {
            (have, want) if have == want => 0,
            // 10 or 12 significant bits in a 16-bit container.
            (16, 10 | 12) if self.packing == Packing::U16Le => 1,
            _ => return None,
        };
        Some((class, fit))
    }
}

/// Why a buffer could not be converted.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum FormatError {
    /// Fewer bytes than the format needs.
    #[error("{got} bytes, {need} needed for {width}×{height}")]
    Short {
        /// Bytes there.
        got: usize,
        /// Bytes needed.
        need: usize,
        /// Width (px).
        width: usize,
        /// Height (px).
        height: usize,
    },
    /// A stride or width the format cannot have.
    #[error("{0}")]
    Layout(String),
    /// The JPEG decoder refused the data.
    #[error("JPEG: {0}")]
    Jpeg(String),
    /// The JPEG has another size than the camera was set to.
    #[error("JPEG is {got_width}×{got_height}, {width}×{height} expected")]
    JpegSize {
        /// Size found.
        got_width: usize,
        /// Size found.
        got_height: usize,
        /// Size expected.
        width: usize,
        /// Size expected.
        height: usize,
    },
}

/// The samples of a `width`×`height` buffer in `data` (`stride` bytes per row, at least the
/// format's [`row_bytes`](SampleFormat::row_bytes)), unpacked one value per sample (three
/// per pixel for RGB / BGR, two for YUYV), row-major; not for JPEG.
pub fn unpack(
    format: &SampleFormat,
    data: &[u8],
    width: usize,
    height: usize,
    stride: usize,
) -> Result<Vec<u16>, FormatError> {
    let row = format
        .row_bytes(width)
        .ok_or_else(|| FormatError::Layout(format!("{width} px wide does not fit {format:?}")))?;
    if stride < row {
        return Err(FormatError::Layout(format!(
            "stride {stride} below the {row} bytes of a row"
        )));
    }
    let need = height.saturating_sub(1) * stride + row;
    if data.len() < need {
        return Err(FormatError::Short {
            got: data.len(),
            need,
            width,
            height,
        });
    }
    let per_row = row_samples(format, width);
    let mut out = Vec::with_capacity(per_row * height);
    for y in 0..height {
        let bytes = &data[y * stride..y * stride + row];
        unpack_row(format.packing, format.bits, bytes, per_row, &mut out);
    }
    Ok(out)
}

/// Samples in one row of `width` pixels.
fn row_samples(format: &SampleFormat, width: usize) -> usize {
    match format.colour {
        Colour::Rgb | Colour::Bgr => 3 * width,
        Colour::YuyvLuma => 2 * width,
        _ => width,
    }
}

/// Append the `n` samples of one row's `bytes` to `out`.
fn unpack_row(packing: Packing, bits: u8, bytes: &[u8], n: usize, out: &mut Vec<u16>) {
    match packing {
        Packing::U8 => out.extend(bytes.iter().map(|&b| u16::from(b))),
        Packing::U16Le => out.extend(
            bytes
                .chunks_exact(2)
                .map(|b| u16::from_le_bytes([b[0], b[1]])),
        ),
        Packing::LsbStream => {
            let mask = (1u32 << bits) - 1;
            let (mut acc, mut have, mut next) = (0u32, 0u8, bytes.iter());
            for _ in 0..n {
                while have < bits {
                    acc |= u32::from(*next.next().unwrap_or(&0)) << have;
                    have += 8;
                }
                out.push((acc & mask) as u16);
                acc >>= bits;
                have -= bits;
            }
        }
        Packing::GvspPair => {
            let low = bits.saturating_sub(8);
            let mask = (1u16 << low) - 1;
            for t in bytes.chunks_exact(3) {
                let (a, m, b) = (u16::from(t[0]), u16::from(t[1]), u16::from(t[2]));
                out.push(a << low | (m & mask));
                out.push(b << low | ((m >> 4) & mask));
            }
        }
    }
}

/// Grey samples in [`Pixels`]: 8-bit for 8 bits, 16-bit otherwise.
pub fn to_pixels(samples: Vec<u16>, bits: u8) -> Pixels {
    if bits <= 8 {
        Pixels::Gray8(samples.into_iter().map(|v| v.min(255) as u8).collect())
    } else {
        Pixels::Gray16(samples)
    }
}

/// BT.601 luma of interleaved colour samples (three per pixel, `order` RGB or BGR),
/// rounded: (77·R + 150·G + 29·B + 128) / 256.
pub fn luma(samples: &[u16], bgr: bool) -> Vec<u16> {
    samples
        .chunks_exact(3)
        .map(|p| {
            let (r, g, b) = match bgr {
                false => (p[0], p[1], p[2]),
                true => (p[2], p[1], p[0]),
            };
            ((77 * u32::from(r) + 150 * u32::from(g) + 29 * u32::from(b) + 128) >> 8) as u16
        })
        .collect()
}

/// Gains (red, green, blue) that bring each channel of a Bayer mosaic to green's level on a
/// neutral scene, measured over the bright 2×2 cells only: those whose first green sample
/// reaches `min_level`. Over them, the gain of red (blue) is the sum of the cells' second
/// green sample over the sum of their red (blue) samples: the second green, not the one
/// that chose the cell, so the choice does not bias the ratio by its noise, and no dark
/// region enters (the black background's clipped noise and any black level are offsets
/// that would pull a whole-frame ratio towards 1). `None` when fewer than one cell in a
/// thousand is bright (a frame too dark to tell) or a channel is black there.
pub fn grey_world_gains(
    mosaic: &[u16],
    width: usize,
    cfa: Cfa,
    min_level: f64,
) -> Option<[f64; 3]> {
    let (w, h) = (width & !1, (mosaic.len() / width.max(1)) & !1);
    let (mut sum, mut cells, mut bright) = ([0f64; 3], 0usize, 0usize);
    for y in (0..h).step_by(2) {
        for x in (0..w).step_by(2) {
            cells += 1;
            // The cell's four samples by channel; its two greens in reading order.
            let mut greens = [0f64; 2];
            let (mut red, mut blue, mut g) = (0f64, 0f64, 0);
            for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                let v = f64::from(mosaic[(y + dy) * width + x + dx]);
                match cfa.channel(x + dx, y + dy) {
                    0 => red = v,
                    2 => blue = v,
                    _ => {
                        greens[g] = v;
                        g += 1;
                    }
                }
            }
            if greens[0] >= min_level {
                bright += 1;
                sum[0] += red;
                sum[1] += greens[1];
                sum[2] += blue;
            }
        }
    }
    if bright == 0 || bright * 1000 < cells || sum[0] <= 0.0 || sum[2] <= 0.0 {
        return None;
    }
    Some([sum[1] / sum[0], 1.0, sum[1] / sum[2]])
}

/// Multiply each sample of a Bayer mosaic by its channel's gain, rounded and clamped to
/// `max` (the format's full scale).
pub fn balance_mosaic(mosaic: &mut [u16], width: usize, cfa: Cfa, gains: [f64; 3], max: u16) {
    for (y, row) in mosaic.chunks_mut(width.max(1)).enumerate() {
        for (x, v) in row.iter_mut().enumerate() {
            let g = gains[cfa.channel(x, y)];
            *v = (f64::from(*v) * g).round().min(f64::from(max)) as u16;
        }
    }
}

/// The white balance of a Bayer camera over one acquisition: measured by grey world over
/// the bright cells (green ≥ 1/16 of full scale) of the first frame that has enough of them
/// ([`grey_world_gains`]) and held, so a whole phase-shift stack is balanced alike; frames
/// before it are balanced with unit gains (the capture engine shows such a camera a
/// white-lit frame before its first stack).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct BayerBalance {
    gains: Option<[f64; 3]>,
}

impl BayerBalance {
    /// Gains fixed in advance (the rig file's), never measured.
    pub fn fixed(gains: [f64; 3]) -> Self {
        BayerBalance { gains: Some(gains) }
    }

    /// The gains held, if measured or fixed.
    pub fn gains(&self) -> Option<[f64; 3]> {
        self.gains
    }

    /// Balance `mosaic` (`bits` per sample), measuring the gains first if none are held.
    pub fn apply(&mut self, mosaic: &mut [u16], width: usize, cfa: Cfa, bits: u8) {
        let max = ((1u32 << bits) - 1) as u16;
        if self.gains.is_none() {
            self.gains = grey_world_gains(mosaic, width, cfa, f64::from(max) / 16.0);
        }
        if let Some(gains) = self.gains {
            balance_mosaic(mosaic, width, cfa, gains, max);
        }
    }
}

/// The luma plane of a JPEG image that must be `width`×`height` (8 bits). The data must end
/// with the end-of-image marker (trailing zero padding allowed): a frame cut short in
/// transfer is refused rather than decoded with its missing part filled in.
pub fn jpeg_luma(data: &[u8], width: usize, height: usize) -> Result<Vec<u8>, FormatError> {
    let end = data.len() - data.iter().rev().take_while(|&&b| b == 0).count();
    if !data[..end].ends_with(&[0xFF, 0xD9]) {
        return Err(FormatError::Jpeg(
            "no end-of-image marker (frame cut short)".into(),
        ));
    }
    use zune_jpeg::zune_core::bytestream::ZCursor;
    use zune_jpeg::zune_core::colorspace::ColorSpace;
    use zune_jpeg::zune_core::options::DecoderOptions;
    let options = DecoderOptions::default()
        .set_max_width(width)
        .set_max_height(height)
        .jpeg_set_out_colorspace(ColorSpace::Luma);
    let mut decoder = zune_jpeg::JpegDecoder::new_with_options(ZCursor::new(data), options);
    decoder
        .decode_headers()
        .map_err(|e| FormatError::Jpeg(e.to_string()))?;
    let (got_width, got_height) = decoder
        .dimensions()
        .ok_or_else(|| FormatError::Jpeg("no frame header".into()))?;
    if (got_width, got_height) != (width, height) {
        return Err(FormatError::JpegSize {
            got_width,
            got_height,
            width,
            height,
        });
    }
    let out = decoder
        .decode()
        .map_err(|e| FormatError::Jpeg(e.to_string()))?;
    if out.len() != width * height {
        return Err(FormatError::Jpeg(format!(
            "{} luma samples decoded, {} expected",
            out.len(),
            width * height
        )));
    }
    Ok(out)
}

/// One frame of `format` to grey: unpacked, RGB to luma, a JPEG decoded to its luma; a
/// Bayer mosaic balanced by `balance` (held across calls). `stride` is bytes per row
/// (ignored for JPEG, whose `data` is the whole coded frame).
pub fn to_grey(
    format: &SampleFormat,
    data: &[u8],
    width: usize,
    height: usize,
    stride: usize,
    balance: &mut BayerBalance,
) -> Result<Pixels, FormatError> {
    let samples = match format.colour {
        Colour::Jpeg => return Ok(Pixels::Gray8(jpeg_luma(data, width, height)?)),
        Colour::Mono => unpack(format, data, width, height, stride)?,
        Colour::YuyvLuma => unpack(format, data, width, height, stride)?
            .into_iter()
            .step_by(2)
            .collect(),
        Colour::Rgb | Colour::Bgr => luma(
            &unpack(format, data, width, height, stride)?,
            format.colour == Colour::Bgr,
        ),
        Colour::Bayer(cfa) => {
            let mut mosaic = unpack(format, data, width, height, stride)?;
            balance.apply(&mut mosaic, width, cfa, format.bits);
            mosaic
        }
    };
    Ok(to_pixels(samples, format.bits))
}

#[cfg(test)]
mod tests;
