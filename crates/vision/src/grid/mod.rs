//! Grid building (docs/design.md §5): local hexagonal cells with chord-normalised distances,
//! marker-ring decoding, and breadth-first assembly into one labelled lattice.
//!
//! Takes the detected circles of one image (and the image, to read marker rings) and gives
//! labelled points: lattice position, side when known, and whether the labels are anchored
//! in the side's board frame.
//!
//! - Pass 1 (`cell`): for every circle, its six lattice neighbours from opposing pairs whose
//!   chord-normalised length is d/R, ordered counter-clockwise on screen and checked for
//!   affine consistency; cells with two checked pairs take the third axis from them.
//! - Rings (`ring`): each circle's annulus 0.45R–0.75R is read against its foreground and
//!   background levels; a full cell whose six neighbours read confidently gives a code, and
//!   a code that is a rotation of a board code names a marker kind and rotation.
//! - Pass 2 (`assemble`): breadth-first growth from a seed cell, best cells first; a cell is
//!   placed only when its rotation agrees with every neighbour already placed.
//! - Anchoring (`anchor`): a decoded centre cell proposes the side's board frame; it is
//!   accepted only when the component's other markers and its ring readings agree with the
//!   board, and no other centre hypothesis scores as well. Only that makes a grid anchored:
//!   side marks repeat every 6 steps, so agreeing side marks fix the side and rotation but
//!   not the origin (the labels then differ from the board frame by a translation (6i, 6j));
//!   without them the frame is arbitrary. Anchored labels off the board are dropped, and more
//!   than a few of them refute the anchor.
//!
//! - Joining (`join`): when an occluder splits the cells into several components, the others
//!   join the anchored one (else the largest) across the gap when local homographies predict
//!   their circles onto free lattice positions under one transform, both ways, and (when
//!   anchored) the board's rings agree. Components that do not join are kept as pieces, each
//!   labelled in a frame of its own.
//! - Lattice check (`off_lattice`): a labelled centre far off where a local homography of its
//!   neighbours puts its lattice position — a fit to what an occluder left of a circle — is
//!   dropped.

mod anchor;
mod assemble;
mod cell;
mod join;
mod off_lattice;
mod ring;

use anchor::{BoardRings, Frame, PlacedMarker};
use hexcal_core::board::LatticeMap;
use hexcal_core::board::{Board, Code, Hex, MarkerKind, Side};
use nalgebra::Point2;
use ring::Ring;
use serde::{Deserialize, Serialize};
use {crate::detect::Circle, hexcal_core::images::FloatImage};

/// A detected circle with its lattice label.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct LabelledPoint {
    /// Index into the detections this grid was built from.
    pub circle: usize,
    /// Ellipse centre in the image (px).
    pub image: Point2<f64>,
    /// Lattice position: in the side's board frame when `anchored`, else in an arbitrary but
    /// self-consistent lattice frame shared by all points of the grid.
    pub hex: Hex,
    /// Side seen, when side markers fixed it.
    pub side: Option<Side>,
    /// Whether `hex` and `side` are in that side's own board frame.
    pub anchored: bool,
    /// Whether the circle carries a marker ring: the board's when anchored, else as read (an
    /// unsure reading counts as ringed, so the annulus is kept out of projector fits).
    #[serde(default)]
    pub ringed: bool,
}

/// Tolerances of grid building. The defaults follow docs/design.md §5; the board supplies d/R and
/// the ring radii.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct GridParams {
    /// Candidate neighbours per cell: the nearest in the centre ellipse's metric.
    pub candidates: usize,
    /// Candidates lie within this factor of the nominal neighbour distance d/(2R) (either
    /// way). The next lattice ring sits at √3 times it.
    pub max_neighbour_ratio: f64,
    /// Largest ratio between a neighbour's semi-axes and the centre's along any direction
    /// (either way; the neighbour's ellipse in the centre's whitened frame). Perspective
    /// makes neighbours differ by ≤ 7 % at 75° of tilt (the shared samples), and thin
    /// ellipses' fitted axes scatter by ~10 %; a circle cut by an occluder, fitted to what is
    /// left of it (short across the cut), or a marker's inner disk (0.45 R) differ by far
    /// more.
    pub radius_ratio: f64,
    /// Relative tolerance of an opposing pair's chord-normalised length ν against d/R
    /// (true pairs: within 5 % at r = 5 px; nearest wrong kinds at −13 % and +32 %).
    pub pair_tolerance: f64,
    /// Largest distance of the centre from a pair's midpoint, as a fraction of the pair's
    /// length, in the whitened frame (a wrong pair 120° apart sits at 0.29).
    pub midpoint_tolerance: f64,
    /// Largest angular deviation of a neighbour from its 60° slot in the whitened frame (rad).
    pub slot_tolerance: f64,
    /// Affine consistency of the pair half-differences, P(1) = P(0) + P(2), as a fraction of
    /// the neighbour distance.
    pub pair_affine_tolerance: f64,
    /// Affine consistency of single neighbour vectors, D(k+1) = D(k) + D(k+2), as a fraction
    /// of the neighbour distance (perspective adds second-order terms here).
    pub affine_tolerance: f64,
    /// A ring contrast — (foreground − annulus mean)/(foreground − background), with the
    /// circle's own levels, over the annulus of the scaled outer ellipse — below this reads
    /// plain.
    pub ring_plain_below: f64,
    /// A ring contrast above this reads ringed; between the two the reading is unsure.
    pub ring_ringed_above: f64,
    /// Side marks that must agree (side, rotation, marker lattice) to fix the side.
    pub min_side_marks: usize,
    /// Largest fraction of contradicting ring readings among the confident readings that
    /// bear on a hypothesis (ringed on the board or read ringed).
    pub max_ring_disagreement: f64,
    /// Labelled points an anchored grid may map off the board (they are dropped); more
    /// refute the anchor.
    pub max_off_board: usize,
    /// Reference circles (nearest in the image) a local homography is fitted to when
    /// predicting lattice positions across a gap.
    pub join_support: usize,
    /// Circles on each side of a gap, nearest the other side, whose predictions decide a join.
    pub join_candidates: usize,
    /// Largest distance (pitch units) of a predicted lattice-plane point from the lattice
    /// position it falls on.
    pub join_tolerance: f64,
    /// Largest residual (pitch units) of a local homography on its own circles.
    pub join_fit_tolerance: f64,
    /// Circles a local homography may leave out of its support, worst first, to fit the
    /// rest within `join_fit_tolerance` (a circle cut by the occluder can keep a centre off
    /// by a pixel under blur).
    pub join_fit_outliers: usize,
    /// Predictions that must agree on the joining transform.
    pub min_join_points: usize,
    /// Fraction of the candidates whose predictions must agree.
    pub join_agreement: f64,
}

impl Default for GridParams {
    fn default() -> Self {
        GridParams {
            candidates: 12,
            max_neighbour_ratio: 1.5,
            radius_ratio: 1.4,
            pair_tolerance: 0.07,
            midpoint_tolerance: 0.12,
            slot_tolerance: 15f64.to_radians(),
            pair_affine_tolerance: 0.1,
            affine_tolerance: 0.25,
            // Blur alone darkens a plain annulus by ≤ 0.16 of the contrast down to r = 3.5 px
            // at σ_PSF = 1 px; a ring reads ≥ 0.35 (ring::tests has the model).
            ring_plain_below: 0.22,
            ring_ringed_above: 0.3,
            min_side_marks: 2,
            max_ring_disagreement: 0.2,
            max_off_board: 2,
            join_support: 16,
            join_candidates: 24,
            join_tolerance: 0.25,
            join_fit_tolerance: 0.05,
            join_fit_outliers: 2,
            min_join_points: 6,
            join_agreement: 0.8,
        }
    }
}

/// A decoded marker cell.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct MarkerReading {
    /// The cell's centre circle.
    pub circle: usize,
    /// What the ring code decoded as.
    pub kind: MarkerKind,
    /// Rotation k of the decode: image slot j is board direction (j + k) mod 6.
    pub rotation: u8,
    /// Whether the marker agrees with the labelling that was output (placed in the chosen
    /// grid at a marker cell of its kind, with the grid's rotation).
    pub confirmed: bool,
}

/// What grid building found, for diagnostics.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct GridStats {
    /// Detections given.
    pub circles: usize,
    /// Local cells found in pass 1.
    pub cells: usize,
    /// Of these, cells with all six neighbours.
    pub full_cells: usize,
    /// Detections whose pairs failed the slot or affine checks.
    pub inconsistent_cells: usize,
    /// Circles read ringed.
    pub ringed: usize,
    /// Circles whose ring reading was unsure.
    pub unsure_rings: usize,
    /// Every decoded marker cell.
    pub markers: Vec<MarkerReading>,
    /// Sizes (labelled points) of the connected components before joining, the chosen one
    /// first.
    pub components: Vec<usize>,
    /// Cells rejected in pass 2 because they disagreed with the labelling around them.
    pub conflicts: usize,
    /// Labelled points dropped because the anchored frame put them off the board.
    pub off_board: usize,
    /// Ring readings that contradict the output labelling (anchored grids only).
    pub ring_disagreements: usize,
    /// Components joined across gaps (into the grid or into its pieces).
    #[serde(default)]
    pub joined: usize,
    /// Sizes (labelled points) of the pieces left beside the grid after joining.
    #[serde(default)]
    pub pieces: Vec<usize>,
    /// Labelled points dropped (from the grid and its pieces) because their centres lie off
    /// the lattice their neighbours predict: fits to what an occluder left of a circle.
    #[serde(default)]
    pub off_lattice: usize,
}

/// The labelled grid of one image.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Grid {
    /// One point per labelled circle.
    pub points: Vec<LabelledPoint>,
    /// Whether the labels are in the side's board frame.
    pub anchored: bool,
    /// The side seen, when known.
    pub side: Option<Side>,
    /// Diagnostics.
    pub stats: GridStats,
    /// Components that could not be joined to this grid, each labelled in a frame of its own
    /// (never anchored: only calibration can place them on the board). Their own `pieces`
    /// are empty.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub pieces: Vec<Grid>,
}

/// What grid building reads from one image, shared by its steps.
struct Scene<'a> {
    circles: &'a [Circle],
    board: &'a Board,
    params: &'a GridParams,
    cells: Vec<cell::Cell>,
    readings: Vec<Ring>,
    decoded: Vec<Option<(MarkerKind, usize)>>,
    rings: BoardRings,
}

/// Build the labelled grid of one image from its detected circles (docs/design.md §5).
pub fn build(image: &FloatImage, circles: &[Circle], board: &Board, params: &GridParams) -> Grid {
    let (scene, mut stats) = Scene::read(image, circles, board, params);
    // Pass 2: seeds are centre cells first, then the best cells.
    let mut assembler = assemble::Assembler::new(&scene.cells, circles.len());
    let mut seeds = assembler.by_quality();
    seeds.sort_by_key(|&k| !scene.decoded[k].is_some_and(|(kind, _)| kind.is_center()));
    let mut components = Vec::new();
    for k in seeds {
        if assembler.can_seed(k) {
            let id = components.len() as u32;
            components.push(assembler.grow(id, k));
        }
    }
    stats.conflicts = components.iter().map(|c| c.rejected).sum();
    // The anchored component if any (most agreeing markers), else the largest.
    let frames: Vec<Frame> = components.iter().map(|c| scene.frame(c)).collect();
    let Some(best) = (0..components.len()).max_by_key(|&i| {
        let f = &frames[i];
        (
            f.anchored,
            f.anchored.then_some(f.evidence.markers_agree),
            components[i].points.len(),
        )
    }) else {
        stats.markers = marker_readings(&scene.cells, &scene.decoded, &[]);
        return Grid {
            stats,
            ..Grid::default()
        };
    };
    let mut reference = components.swap_remove(best);
    stats.components = std::iter::once(reference.points.len())
        .chain(components.iter().map(|c| c.points.len()))
        .collect();
    let (grid, mut pieces) = scene.join(&mut reference, components, frames[best], &mut stats);
    stats.off_lattice = std::iter::once(&mut reference)
        .chain(pieces.iter_mut())
        .map(|c| off_lattice::drop_off_lattice(c, circles, params))
        .sum();
    let mut grid = scene.output(&reference, grid, stats);
    grid.pieces = pieces
        .iter()
        .map(|p| {
            let frame = Frame {
                anchored: false,
                ..scene.frame(p)
            };
            scene.output(p, frame, GridStats::default())
        })
        .collect();
    grid
}

impl<'a> Scene<'a> {
    /// Pass 1 and the ring readings: every circle's local cell, its ring, and the decoded
    /// marker cells.
    fn read(
        image: &FloatImage,
        circles: &'a [Circle],
        board: &'a Board,
        params: &'a GridParams,
    ) -> (Scene<'a>, GridStats) {
        let nu = board.pitch / board.radius;
        let found = cell::find_cells(circles, nu, params);
        let mut stats = GridStats {
            circles: circles.len(),
            inconsistent_cells: found
                .iter()
                .filter(|c| matches!(c, Err(cell::Rejection::Inconsistent)))
                .count(),
            ..GridStats::default()
        };
        let cells: Vec<cell::Cell> = found.into_iter().filter_map(Result::ok).collect();
        stats.cells = cells.len();
        stats.full_cells = cells.iter().filter(|c| c.is_full()).count();
        let readings = read_rings(image, circles, &cells, board, params);
        stats.ringed = readings.iter().filter(|&&r| r == Ring::Ringed).count();
        stats.unsure_rings = readings.iter().filter(|&&r| r == Ring::Unsure).count();
        let decoded = cells.iter().map(|c| decode(c, &readings, board)).collect();
        let scene = Scene {
            circles,
            board,
            params,
            cells,
            readings,
            decoded,
            rings: BoardRings::new(board),
        };
        (scene, stats)
    }

    /// A component's frame from its markers and rings.
    fn frame(&self, comp: &assemble::Component) -> Frame {
        let markers = placed_markers(comp, &self.cells, &self.decoded);
        anchor::frame(
            self.board,
            &self.rings,
            comp,
            &markers,
            &self.readings,
            self.params,
        )
    }

    /// Whether `comp`, moved by `map` into a component anchored by `frame`, agrees with the
    /// board: its markers at marker cells of their kind, its ring readings and its outline.
    fn admits(&self, frame: Frame, comp: &assemble::Component, map: LatticeMap) -> bool {
        let Some(side) = frame.side else {
            return false;
        };
        let to_board = map.then(frame.map);
        let markers = placed_markers(comp, &self.cells, &self.decoded);
        let ev = anchor::weigh(
            self.board,
            &self.rings,
            comp,
            &markers,
            &self.readings,
            side,
            to_board,
        );
        let bearing = ev.rings_agree + ev.rings_disagree;
        ev.markers_disagree <= ev.markers_agree
            && ev.rings_disagree as f64 <= self.params.max_ring_disagreement * bearing as f64
            && ev.off_board <= self.params.max_off_board
    }

    /// Join components across gaps into `reference` (anchored by `frame` or not), then the
    /// rest among themselves, largest first. Gives the reference's frame after joining and
    /// the pieces left.
    fn join(
        &self,
        reference: &mut assemble::Component,
        mut rest: Vec<assemble::Component>,
        frame: Frame,
        stats: &mut GridStats,
    ) -> (Frame, Vec<assemble::Component>) {
        let centres: Vec<Point2<f64>> = self.circles.iter().map(|c| c.ellipse.center).collect();
        let admit =
            |c: &assemble::Component, m: LatticeMap| !frame.anchored || self.admits(frame, c, m);
        stats.joined = join::join_into(reference, &mut rest, &centres, self.params, &admit);
        // Joined markers may fix the side of an unanchored reference.
        let frame = if frame.anchored {
            frame
        } else {
            self.frame(reference)
        };
        let mut pieces = Vec::new();
        while !rest.is_empty() {
            let mut piece = rest.remove(0);
            stats.joined +=
                join::join_into(&mut piece, &mut rest, &centres, self.params, &|_, _| true);
            pieces.push(piece);
        }
        stats.pieces = pieces.iter().map(|p| p.points.len()).collect();
        (frame, pieces)
    }

    /// The labelled points of a component in `frame`, its markers and the remaining stats.
    fn output(&self, comp: &assemble::Component, frame: Frame, mut stats: GridStats) -> Grid {
        let board_rings = frame
            .side
            .filter(|_| frame.anchored)
            .map(|s| self.board.ringed(s));
        let mut points = Vec::with_capacity(comp.points.len());
        for &(circle, h) in &comp.points {
            let hex = frame.map.apply(h);
            if frame.anchored && !self.board.contains(hex) {
                stats.off_board += 1;
                continue;
            }
            points.push(LabelledPoint {
                circle: circle as usize,
                image: self.circles[circle as usize].ellipse.center,
                hex,
                side: frame.side,
                anchored: frame.anchored,
                ringed: board_rings
                    .as_ref()
                    .map_or(self.readings[circle as usize] != Ring::Plain, |ringed| {
                        ringed.contains(&hex)
                    }),
            });
        }
        points.sort_by_key(|p| p.circle);
        if frame.anchored {
            stats.ring_disagreements = frame.evidence.rings_disagree;
        }
        let confirmed: Vec<PlacedMarker> = placed_markers(comp, &self.cells, &self.decoded)
            .into_iter()
            .filter(|m| frame.confirms(m, &self.rings, self.board.marker_spacing.unwrap_or(1)))
            .collect();
        stats.markers = marker_readings(&self.cells, &self.decoded, &confirmed);
        Grid {
            points,
            anchored: frame.anchored,
            side: frame.side,
            stats,
            pieces: Vec::new(),
        }
    }
}

/// Every circle's ring reading. A ring dims a small circle's own foreground level (blur
/// darkens the white left around it), which would hide the ring: each ring is read against
/// the brightest foreground of the cells it belongs to. Every ringed circle neighbours its
/// marker's plain centre.
fn read_rings(
    image: &FloatImage,
    circles: &[Circle],
    cells: &[cell::Cell],
    board: &Board,
    params: &GridParams,
) -> Vec<Ring> {
    let mut white: Vec<f32> = circles.iter().map(|c| c.foreground).collect();
    for cell in cells {
        let top = cell
            .members()
            .map(|(_, i)| circles[i as usize].foreground)
            .fold(f32::MIN, f32::max);
        for (_, i) in cell.members() {
            white[i as usize] = white[i as usize].max(top);
        }
    }
    circles
        .iter()
        .zip(&white)
        .map(|(c, &white)| {
            let contrast = ring::ring_contrast(image, c, white, board.ring);
            ring::classify(contrast, params.ring_plain_below, params.ring_ringed_above)
        })
        .collect()
}

/// Decode a full cell whose centre is not ringed and whose six neighbours read confidently.
fn decode(c: &cell::Cell, readings: &[Ring], board: &Board) -> Option<(MarkerKind, usize)> {
    if readings[c.center as usize] == Ring::Ringed {
        return None;
    }
    let mut code = 0u8;
    for (j, slot) in c.slots.iter().enumerate() {
        match readings[(*slot)? as usize] {
            Ring::Ringed => code |= 1 << j,
            Ring::Plain => {}
            Ring::Unsure => return None,
        }
    }
    board.codes.decode(Code(code))
}

/// The decoded cells placed in a component, in its frame.
fn placed_markers(
    comp: &assemble::Component,
    cells: &[cell::Cell],
    decoded: &[Option<(MarkerKind, usize)>],
) -> Vec<PlacedMarker> {
    comp.cells
        .iter()
        .filter_map(|p| {
            let (kind, rotation) = decoded[p.cell]?;
            Some(PlacedMarker {
                circle: cells[p.cell].center,
                kind,
                at: p.centre,
                // Slot j is frame direction j + ρ and board direction j + k.
                rotation: ((rotation + 6 - p.rotation as usize) % 6) as u8,
            })
        })
        .collect()
}

/// Every decoded cell, marked confirmed when it agrees with the output labelling.
fn marker_readings(
    cells: &[cell::Cell],
    decoded: &[Option<(MarkerKind, usize)>],
    confirmed: &[PlacedMarker],
) -> Vec<MarkerReading> {
    cells
        .iter()
        .zip(decoded)
        .filter_map(|(c, d)| {
            let (kind, rotation) = (*d)?;
            Some(MarkerReading {
                circle: c.center as usize,
                kind,
                rotation: rotation as u8,
                confirmed: confirmed.iter().any(|m| m.circle == c.center),
            })
        })
        .collect()
}
