//! One camera's stack of one pose through the stages: decode, detect, grid, projector fits.
//!
//! Takes the camera's frames as they arrive (or a decoded stack); gives a [`StackResult`]
//! with the labelled view. On a rig without projectors the stack is one plain frame, on
//! which circles are detected directly (no decoding, no projector fits). `pose-KKK/views.json` ([`PoseViews`]) holds every camera's
//! result of a pose.

use crate::board::Board;
use crate::correspond::{camera_view, FitParams, ProjectorMap};
use crate::dataset::StackReader;
use crate::dataset::{CameraEntry, Dataset, DatasetError, DatasetInfo};
use crate::detect::{detect, DetectParams};
use crate::grid::{build, GridParams};
use crate::images::{CameraFrame, FloatImage, Pixels};
use crate::invalid::{Invalid, ValidationError};
use crate::observations::CameraView;
use crate::pattern::Sequence;
use crate::phase::check::StackVerdict;
use crate::phase::files::decode_stack;
use crate::phase::{CompactStack, DecodedStack, Decoder, FrameRef};
use crossbeam_channel::Receiver;
use serde::{Deserialize, Serialize};

/// What one camera's stack of one pose gave.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StackResult {
    /// Camera name.
    pub camera: String,
    /// Circles detected.
    pub circles: usize,
    /// Labelled board points.
    pub points: usize,
    /// Whether the labels are in the board's own frame (the centre cell was seen).
    pub anchored: bool,
    /// Per projector (sequence order): points with a projector pixel.
    pub projector_points: Vec<usize>,
    /// Why the stack gave nothing, if it did not.
    pub error: Option<String>,
    /// The labelled view (none when the board was not found or the stack was refused).
    pub view: Option<CameraView>,
    /// The stack check's verdict (docs/design.md §6b); none for a camera-only pose.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub verdict: Option<StackVerdict>,
}

impl StackResult {
    /// A stack of camera `camera` that gave nothing, and why.
    fn failed(camera: &str, projectors: usize, error: String) -> StackResult {
        StackResult {
            camera: camera.to_string(),
            circles: 0,
            points: 0,
            anchored: false,
            projector_points: vec![0; projectors],
            error: Some(error),
            view: None,
            verdict: None,
        }
    }

    /// The stack of camera `camera` that failed the stack check: not used.
    fn refused(camera: &str, projectors: usize, verdict: &StackVerdict) -> StackResult {
        StackResult {
            verdict: Some(verdict.clone()),
            ..StackResult::failed(camera, projectors, refusal(verdict))
        }
    }
}

/// The reason a refused stack gives: its faults, one line.
pub fn refusal(verdict: &StackVerdict) -> String {
    format!("stack refused: {}", verdict.summary())
}

/// The stored plain frame of a camera-only pose (its frame 0) as a float image.
fn read_plain_frame(stack: &StackReader) -> Result<FloatImage, DatasetError> {
    let pixels = stack.frame(0)?;
    let (w, h) = (stack.info.width, stack.info.height);
    float_image(w, h, &Pixels::Gray16(pixels)).ok_or_else(|| DatasetError::Invalid {
        path: stack.dir().to_owned(),
        reason: format!("frame 0 is not {w}×{h}"),
    })
}

/// `pose-KKK/views.json`: every camera's result for one pose.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PoseViews {
    /// Pose index.
    pub pose: usize,
    /// Per camera, in rig order.
    pub stacks: Vec<StackResult>,
}

impl crate::dataset::PoseFile for PoseViews {
    /// `views.json` of pose `pose`: its own pose index, one result per camera of the
    /// dataset in order, one projector count per projector, and every view of its own
    /// camera and pose with projector indices among the dataset's projectors (device
    /// indices: cameras first, then projectors).
    fn check(&self, pose: usize, info: &DatasetInfo) -> Result<(), ValidationError> {
        if self.pose != pose {
            return Err(ValidationError::new(
                "pose",
                format!("{} in the folder of pose {pose}", self.pose),
            ));
        }
        let (cameras, projectors) = (info.cameras.len(), info.projectors.len());
        if self.stacks.len() != cameras {
            return Err(ValidationError::new(
                "stacks",
                format!("{} results for {cameras} cameras", self.stacks.len()),
            ));
        }
        for (c, (s, entry)) in self.stacks.iter().zip(&info.cameras).enumerate() {
            let at = |k: &str| format!("stacks[{c}].{k}");
            if s.camera != entry.name {
                return Err(ValidationError::new(
                    at("camera"),
                    format!("{:?}, but camera {c} is {:?}", s.camera, entry.name),
                ));
            }
            if s.projector_points.len() != projectors {
                return Err(ValidationError::new(
                    at("projector_points"),
                    format!(
                        "{} counts for {projectors} projectors",
                        s.projector_points.len()
                    ),
                ));
            }
            if let Some(v) = &s.verdict {
                v.check().map_err(|e| e.within(format!("stacks[{c}]")))?;
            }
            let Some(view) = &s.view else { continue };
            let camera = |i: usize| match i == c {
                true => Ok(()),
                false => Err(Invalid(format!("camera {i} in the result of camera {c}"))),
            };
            let projector = |j: usize| match (cameras..cameras + projectors).contains(&j) {
                true => Ok(()),
                false => Err(Invalid(format!(
                    "device {j} is not one of the {projectors} projectors (devices from \
                     {cameras} on)"
                ))),
            };
            if view.pose != pose {
                return Err(ValidationError::new(
                    at("view.pose"),
                    format!("{} in the folder of pose {pose}", view.pose),
                ));
            }
            view.check(&camera, &projector, pose + 1)
                .map_err(|e| e.map_at(|k| at(&format!("view.{k}"))))?;
        }
        Ok(())
    }
}

/// Detection, grid and projector fits on one camera's decoded stack (circles on the decoded
/// ambient image: evenly lit and averaged over the stack). `camera` is the camera's device
/// index, `first_projector` the device index of projector 0.
pub fn process_decoded(
    decoded: &DecodedStack,
    board: &Board,
    camera: usize,
    pose: usize,
    first_projector: usize,
) -> StackResult {
    checked(
        &decoded.verdict,
        &decoded.camera,
        decoded.projectors.len(),
        || view_of_decoded(decoded, board, camera, pose, first_projector),
    )
}

/// [`process_decoded`] whatever the stack check's verdict (which it records): `hexcal
/// decode` judging one stack on its own.
pub fn view_of_decoded(
    decoded: &DecodedStack,
    board: &Board,
    camera: usize,
    pose: usize,
    first_projector: usize,
) -> StackResult {
    let maps: Vec<ProjectorMap> = decoded
        .projectors
        .iter()
        .enumerate()
        .map(|(p, m)| ProjectorMap::from_decoded(first_projector + p, m))
        .collect();
    let at = ViewAt {
        camera,
        pose,
        first_projector,
    };
    StackResult {
        verdict: Some(decoded.verdict.clone()),
        ..process_image(&decoded.ambient, &decoded.camera, board, &maps, at)
    }
}

/// The stack processed when it passed the stack check (its verdict recorded), else refused.
fn checked(
    verdict: &StackVerdict,
    camera: &str,
    projectors: usize,
    process: impl FnOnce() -> StackResult,
) -> StackResult {
    if !verdict.passed() {
        return StackResult::refused(camera, projectors, verdict);
    }
    StackResult {
        verdict: Some(verdict.clone()),
        ..process()
    }
}

/// Detection, grid and projector fits on one camera's compactly held stack: each
/// projector's maps are read in place through the pixels' slots (4 bytes per pixel, for
/// this call only).
pub fn process_compact(
    stack: &CompactStack,
    board: &Board,
    camera: usize,
    pose: usize,
    first_projector: usize,
) -> StackResult {
    let slots = stack.candidate_slots();
    let maps: Vec<ProjectorMap> = (0..stack.projectors.len())
        .map(|p| ProjectorMap::from_compact(first_projector + p, stack, p, &slots))
        .collect();
    let at = ViewAt {
        camera,
        pose,
        first_projector,
    };
    checked(&stack.verdict, &stack.camera, maps.len(), || {
        process_image(&stack.ambient, &stack.camera, board, &maps, at)
    })
}

/// Where a processed image belongs: the camera's device index, the pose, and the device
/// index of projector 0.
#[derive(Clone, Copy, Debug)]
pub struct ViewAt {
    /// The camera's device index.
    pub camera: usize,
    /// The board pose.
    pub pose: usize,
    /// Device index of projector 0 (the number of cameras).
    pub first_projector: usize,
}

/// Detection, grid and, for each of `maps`, the projector fits on one camera's image of the
/// board: the decoded ambient image, or the plain frame of a camera-only rig (no maps).
pub fn process_image(
    image: &FloatImage,
    name: &str,
    board: &Board,
    maps: &[ProjectorMap],
    at: ViewAt,
) -> StackResult {
    let circles = detect(image, &DetectParams::default());
    let grid = build(image, &circles, board, &GridParams::default());
    let view = camera_view(
        at.camera,
        at.pose,
        &grid,
        &circles,
        maps,
        &FitParams::for_board(board),
    );
    let projector_points = (0..maps.len())
        .map(|p| {
            view.as_ref().map_or(0, |v| {
                v.points
                    .iter()
                    .filter(|pt| {
                        pt.projectors
                            .iter()
                            .any(|q| q.projector == at.first_projector + p)
                    })
                    .count()
            })
        })
        .collect();
    StackResult {
        camera: name.to_string(),
        circles: circles.len(),
        points: grid.points.len(),
        anchored: grid.anchored,
        projector_points,
        error: None,
        view,
        verdict: None,
    }
}

/// A frame's samples as a linear float image.
fn float_image(width: u32, height: u32, pixels: &Pixels) -> Option<FloatImage> {
    let data: Vec<f32> = match pixels {
        Pixels::Gray8(p) => p.iter().map(|&v| f32::from(v)).collect(),
        Pixels::Gray16(p) => p.iter().map(|&v| f32::from(v)).collect(),
    };
    FloatImage::from_raw(width, height, data)
}

/// The one plain frame of a camera-only pose (`frames` gives it) through detection and
/// grid building.
fn camera_only_worker(frames: &Receiver<CameraFrame>, job: &StackJob) -> StackResult {
    let failed = |error: String| StackResult::failed(&job.entry.name, 0, error);
    let Ok(f) = frames.recv() else {
        return failed("no frame arrived".into());
    };
    let Some(image) = float_image(f.width, f.height, &f.pixels) else {
        return failed(format!(
            "{} samples for a {}×{} frame",
            f.pixels.len(),
            f.width,
            f.height
        ));
    };
    let at = ViewAt {
        camera: job.camera,
        pose: job.pose,
        first_projector: job.first_projector,
    };
    process_image(&image, &job.entry.name, &job.board, &[], at)
}

/// A decoder of 8- or 16-bit frames, chosen by the first frame.
enum AnyDecoder {
    Eight(Decoder<u8>),
    Sixteen(Decoder<u16>),
}

/// The turns the stacks of one pose take one at a time.
#[derive(Default)]
pub(crate) struct Turns {
    /// Taken while a decoder's final pass makes its compact stack.
    pub(crate) judge: std::sync::Mutex<()>,
    /// Taken while a compact stack is spread over its image and processed.
    pub(crate) process: std::sync::Mutex<()>,
}

/// One camera's stack of one pose to decode and process.
pub(crate) struct StackJob {
    pub(crate) sequence: Sequence,
    pub(crate) entry: CameraEntry,
    pub(crate) board: Board,
    pub(crate) camera: usize,
    pub(crate) pose: usize,
    pub(crate) first_projector: usize,
    /// The pose's turns: one stack at a time finishes its decoder, one at a time is processed.
    pub(crate) turns: std::sync::Arc<Turns>,
    /// Hears the stack check's verdict once the stack is compact (its decoder freed), then
    /// dropped (or dropped on failure): the run waits for every camera's before the next
    /// pose's decoders fill, and captures the pose again when a verdict fails.
    pub(crate) decoded: crossbeam_channel::Sender<(usize, StackVerdict)>,
}

/// Decode one camera's stack as its frames arrive on `frames`, then process it.
pub(crate) fn stack_worker(frames: Receiver<CameraFrame>, job: StackJob) -> StackResult {
    if job.sequence.is_camera_only() {
        return camera_only_worker(&frames, &job);
    }
    let StackJob {
        sequence,
        entry,
        board,
        camera,
        pose,
        first_projector,
        turns,
        decoded: decoded_signal,
    } = job;
    let failed =
        |error: String| StackResult::failed(&entry.name, sequence.projectors().len(), error);
    let full_scale = ((1u32 << entry.bits.min(16)) - 1) as f32;
    let mut decoder = None;
    for k in 0..sequence.frame_count() {
        let Ok(f) = frames.recv() else {
            return failed(format!("stack ended after {k} frames"));
        };
        let dec = decoder.get_or_insert_with(|| match f.pixels {
            Pixels::Gray8(_) => Decoder::new(&sequence, &entry.name, f.width, f.height, full_scale)
                .map(AnyDecoder::Eight),
            Pixels::Gray16(_) => {
                Decoder::new(&sequence, &entry.name, f.width, f.height, full_scale)
                    .map(AnyDecoder::Sixteen)
            }
        });
        let pushed = match (dec, &f.pixels) {
            (Ok(AnyDecoder::Eight(d)), Pixels::Gray8(p)) => d.push_frame(
                k,
                FrameRef {
                    width: f.width,
                    height: f.height,
                    pixels: p,
                },
            ),
            (Ok(AnyDecoder::Sixteen(d)), Pixels::Gray16(p)) => d.push_frame(
                k,
                FrameRef {
                    width: f.width,
                    height: f.height,
                    pixels: p,
                },
            ),
            (Err(e), _) => return failed(e.to_string()),
            _ => return failed(format!("frame {k}: sample depth changed within the stack")),
        };
        if let Err(e) = pushed {
            return failed(e.to_string());
        }
    }
    // The maps at once, held compactly (the decoder's buffers are freed) while the stack
    // waits for its turn to be processed. One stack at a time finishes (its decoder and its
    // compact maps are both held while it does: the pose's other decoders wait rather than
    // all doubling at once) and one at a time spreads its maps over the image and detects
    // (bounds the memory of full-image maps while the next pose's decoders fill up).
    let decoded = {
        let _turn = turns.judge.lock().unwrap_or_else(|e| e.into_inner());
        match decoder {
            Some(Ok(AnyDecoder::Eight(d))) => d.finish_compact(),
            Some(Ok(AnyDecoder::Sixteen(d))) => d.finish_compact(),
            Some(Err(e)) => return failed(e.to_string()),
            None => return failed("empty sequence".into()),
        }
    };
    if let Ok(d) = &decoded {
        let _ = decoded_signal.send((camera, d.verdict.clone()));
    }
    drop(decoded_signal);
    let _turn = turns.process.lock().unwrap_or_else(|e| e.into_inner());
    match decoded {
        Ok(d) => process_compact(&d, &board, camera, pose, first_projector),
        Err(e) => failed(e.to_string()),
    }
}

/// Every camera's stack of pose `k` stored in `data`, decoded and processed.
pub fn process_stored(data: &Dataset, board: &Board, k: usize) -> PoseViews {
    let cameras = data.info.cameras.len();
    let stacks = data
        .info
        .cameras
        .iter()
        .enumerate()
        .map(|(c, entry)| {
            let at = ViewAt {
                camera: c,
                pose: k,
                first_projector: cameras,
            };
            let result = data.stack(k, &entry.name).map_err(|e| e.to_string());
            let result = match data.info.sequence.is_camera_only() {
                true => result.and_then(|stack| {
                    read_plain_frame(&stack)
                        .map(|image| process_image(&image, &entry.name, board, &[], at))
                        .map_err(|e| e.to_string())
                }),
                false => result.and_then(|stack| {
                    decode_stack(&stack)
                        .map(|d| process_decoded(&d, board, c, k, cameras))
                        .map_err(|e| e.to_string())
                }),
            };
            result
                .unwrap_or_else(|e| StackResult::failed(&entry.name, data.info.projectors.len(), e))
        })
        .collect();
    PoseViews { pose: k, stacks }
}
