//! The image stages on numpy arrays: circle detection and grid labelling of a grey image
//! (`hexcal detect`), and the phase decoder on a camera's stack of frames (`hexcal decode`).

use crate::arrays::{json_input, rows_array};
use crate::error::{error, guard};
use hexcal_core::board::{Board, Side};
use hexcal_core::images::FloatImage;
use hexcal_core::pattern::Sequence;
use hexcal_vision::detect::{detect as detect_circles, DetectParams};
use hexcal_vision::grid::{build, GridParams};
use hexcal_vision::phase::{DecodeError, DecodedStack, Decoder, FrameRef, Mask, Sample};
use numpy::ndarray::{Array1, Array2, ArrayView3};
use numpy::{IntoPyArray, PyArray1, PyArray2, PyArrayMethods, PyReadonlyArray2, PyReadonlyArray3};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};

/// A grey image (H × W, uint8, uint16, float32 or float64) as hexcal's float image, on the
/// array's own scale (as `hexcal detect` reads a file).
fn grey(image: &Bound<'_, PyAny>) -> PyResult<FloatImage> {
    fn of<T: numpy::Element + Copy>(
        a: &PyReadonlyArray2<'_, T>,
        f: impl Fn(T) -> f32,
    ) -> PyResult<FloatImage> {
        let v = a.as_array();
        let (h, w) = v.dim();
        let (w, h) = (
            u32::try_from(w).map_err(|_| error("image: too wide"))?,
            u32::try_from(h).map_err(|_| error("image: too tall"))?,
        );
        hexcal_core::limits::image_size(w, h).map_err(|m| error(format!("image: {m}")))?;
        Ok(FloatImage::from_raw(w, h, v.iter().map(|&x| f(x)).collect()).expect("w × h values"))
    }
    if let Ok(a) = image.extract::<PyReadonlyArray2<'_, u8>>() {
        return of(&a, f32::from);
    }
    if let Ok(a) = image.extract::<PyReadonlyArray2<'_, u16>>() {
        return of(&a, f32::from);
    }
    if let Ok(a) = image.extract::<PyReadonlyArray2<'_, f32>>() {
        return of(&a, |x| x);
    }
    if let Ok(a) = image.extract::<PyReadonlyArray2<'_, f64>>() {
        return of(&a, |x| x as f32);
    }
    Err(error(
        "image: a 2-D numpy array (H × W) of uint8, uint16, float32 or float64 (grey; \
         convert colour first, e.g. cv2.cvtColor)",
    ))
}

/// Detects the board's circles in a grey image (H × W numpy array of uint8, uint16,
/// float32 or float64; pixel (0, 0) is the centre of the top-left pixel) and labels the
/// lattice, as `hexcal detect` does. `board`: a built-in board name or a board file.
///
/// Returns a dict of numpy arrays: "circles" (N × 4: x, y, radius √(ab), circleness score;
/// strongest first), "points" (M × 2: x, y of the labelled circles), "hex" (M × 2 int32:
/// lattice q, r), "circle" (M int64: row in "circles"), "side" (M int8: 0 front, 1 back,
/// −1 unknown), "anchored" (M bool: q, r and side in that side's own board frame).
#[pyfunction]
#[pyo3(signature = (image, board = "hex600"))]
pub fn detect<'py>(
    py: Python<'py>,
    image: &Bound<'py, PyAny>,
    board: &str,
) -> PyResult<Bound<'py, PyDict>> {
    guard(|| {
        let board = Board::resolve(board).map_err(error)?;
        let img = grey(image)?;
        let (circles, grid) = py.detach(|| {
            let circles = detect_circles(&img, &DetectParams::default());
            let grid = build(&img, &circles, &board, &GridParams::default());
            (circles, grid)
        });
        let out = PyDict::new(py);
        let c: Vec<f64> = circles
            .iter()
            .flat_map(|c| {
                let e = &c.ellipse;
                [e.center.x, e.center.y, e.radius(), c.score]
            })
            .collect();
        out.set_item("circles", rows_array(py, c, 4))?;
        let p = &grid.points;
        let xy: Vec<f64> = p.iter().flat_map(|p| [p.image.x, p.image.y]).collect();
        out.set_item("points", rows_array(py, xy, 2))?;
        let hex = Array2::from_shape_fn((p.len(), 2), |(i, j)| match j {
            0 => p[i].hex.q,
            _ => p[i].hex.r,
        });
        out.set_item("hex", hex.into_pyarray(py))?;
        let index: Array1<i64> = p.iter().map(|p| p.circle as i64).collect();
        out.set_item("circle", index.into_pyarray(py))?;
        let side: Array1<i8> = p
            .iter()
            .map(|p| match p.side {
                Some(Side::Front) => 0,
                Some(Side::Back) => 1,
                None => -1,
            })
            .collect();
        out.set_item("side", side.into_pyarray(py))?;
        let anchored: Array1<bool> = p.iter().map(|p| p.anchored).collect();
        out.set_item("anchored", anchored.into_pyarray(py))?;
        Ok(out)
    })
}

/// Feeds every frame of `frames` (K × H × W, row-major) to a decoder; the frames are read
/// where they lie (a C-contiguous array is not copied).
fn decode_frames<T: Sample + numpy::Element>(
    frames: ArrayView3<'_, T>,
    seq: &Sequence,
    camera: &str,
    full_scale: f32,
) -> Result<DecodedStack, DecodeError> {
    let (_, h, w) = frames.dim();
    let (width, height) = (w as u32, h as u32);
    let mut decoder = Decoder::<T>::new(seq, camera, width, height, full_scale)?;
    let mut copy = Vec::new();
    for (i, frame) in frames.outer_iter().enumerate() {
        let pixels = match frame.as_slice() {
            Some(s) => s,
            None => {
                copy.clear();
                copy.extend(frame.iter().copied());
                &copy[..]
            }
        };
        decoder.push_frame(
            i,
            FrameRef {
                width,
                height,
                pixels,
            },
        )?;
    }
    decoder.finish()
}

/// A float image as an H × W numpy array (the buffer is handed over).
fn image_array(py: Python<'_>, img: FloatImage) -> Bound<'_, PyArray2<f32>> {
    let (w, h) = (img.width() as usize, img.height() as usize);
    Array2::from_shape_vec((h, w), img.into_raw())
        .expect("h × w values")
        .into_pyarray(py)
}

/// A mask as an H × W bool numpy array.
fn mask_array<'py>(py: Python<'py>, m: &Mask) -> Bound<'py, PyArray2<bool>> {
    let (w, h) = (m.width() as usize, m.height() as usize);
    PyArray1::from_slice(py, m.as_slice())
        .reshape([h, w])
        .expect("h × w values")
}

/// Decodes one camera's phase-shift stack, as `hexcal decode` does: `frames` is a K × H × W
/// numpy array (uint8, uint16 or float32; frame k of the sequence at index k) or a list of K
/// H × W arrays (stacked, which copies them); `sequence` the sequence the projectors showed
/// (a dict of the dataset's `sequence` layout, docs/dataset.md, or the path of a JSON file
/// holding one). `full_scale` is the saturation level: by default 255 for uint8 and 65535
/// for uint16 (give 4095 for 12-bit samples); required for float32. `camera` names the
/// stack in errors.
///
/// Returns a dict: "projectors", one dict per projector in sequence order with H × W
/// arrays "u", "v" (projector px, (0, 0) a pixel centre; float32, NaN where not
/// unwrapped), "valid" (bool: where (u, v) is trustworthy), "modulation" (DN),
/// "reliability" (rad), and "sigma_u", "sigma_v" (predicted noise, projector px);
/// "ambient" (H × W float32, DN) and "saturated" (H × W bool).
#[pyfunction]
#[pyo3(signature = (frames, sequence, full_scale = None, camera = "camera"))]
pub fn decode<'py>(
    py: Python<'py>,
    frames: &Bound<'py, PyAny>,
    sequence: &Bound<'py, PyAny>,
    full_scale: Option<f32>,
    camera: &str,
) -> PyResult<Bound<'py, PyDict>> {
    guard(|| {
        let (text, origin) = json_input(sequence, "sequence")?;
        let seq: Sequence = serde_json::from_str(&text)
            .map_err(|e| error(format!("{origin}: not a sequence: {e}")))?;
        let frames = if frames.is_instance_of::<PyList>()
            || frames.is_instance_of::<pyo3::types::PyTuple>()
        {
            py.import("numpy")?.call_method1("stack", (frames,))?
        } else {
            frames.clone()
        };
        let scale = |default: Option<f32>| {
            full_scale.or(default).ok_or_else(|| {
                error("full_scale: needed for float32 frames (the saturation level, DN)")
            })
        };
        let decoded = if let Ok(a) = frames.extract::<PyReadonlyArray3<'_, u8>>() {
            let s = scale(Some(255.0))?;
            {
                let v = a.as_array();
                py.detach(|| decode_frames(v, &seq, camera, s))
            }
        } else if let Ok(a) = frames.extract::<PyReadonlyArray3<'_, u16>>() {
            let s = scale(Some(65535.0))?;
            {
                let v = a.as_array();
                py.detach(|| decode_frames(v, &seq, camera, s))
            }
        } else if let Ok(a) = frames.extract::<PyReadonlyArray3<'_, f32>>() {
            let s = scale(None)?;
            {
                let v = a.as_array();
                py.detach(|| decode_frames(v, &seq, camera, s))
            }
        } else {
            return Err(error(
                "frames: a K × H × W numpy array (or a list of H × W arrays) of uint8, \
                 uint16 or float32",
            ));
        }
        .map_err(error)?;
        let out = PyDict::new(py);
        let projectors = PyList::empty(py);
        for p in decoded.projectors {
            let d = PyDict::new(py);
            d.set_item("valid", mask_array(py, &p.valid))?;
            d.set_item("sigma_u", p.noise.sigma_u)?;
            d.set_item("sigma_v", p.noise.sigma_v)?;
            d.set_item("u", image_array(py, p.u))?;
            d.set_item("v", image_array(py, p.v))?;
            d.set_item("modulation", image_array(py, p.modulation))?;
            d.set_item("reliability", image_array(py, p.reliability))?;
            projectors.append(d)?;
        }
        out.set_item("projectors", projectors)?;
        out.set_item("ambient", image_array(py, decoded.ambient))?;
        out.set_item("saturated", mask_array(py, &decoded.saturated))?;
        Ok(out)
    })
}
