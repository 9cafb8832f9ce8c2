//! Pass 2 of grid building (docs/design.md §5): breadth-first growth of a lattice labelling over
//! the local cells, best cells first, placing a cell only when its rotation agrees with every
//! neighbour already placed.

use super::cell::Cell;
use hexcal_core::board::Hex;
use std::cmp::Reverse;
use std::collections::{BinaryHeap, HashMap};

/// What happened to a cell during assembly.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum State {
    /// Not (yet) placeable: fewer than two of its circles are placed.
    Pending,
    /// Placed (its rotation is recorded in its component).
    Placed,
    /// Disagreed with the labelling around it (or touched another component).
    Rejected,
}

/// One connected labelling in its own lattice frame.
#[derive(Clone, Debug, Default)]
pub(crate) struct Component {
    /// (circle, lattice position) of every labelled circle.
    pub points: Vec<(u32, Hex)>,
    /// Every placed cell.
    pub cells: Vec<PlacedCell>,
    /// Cells rejected because they disagreed with this component.
    pub rejected: usize,
}

/// A cell placed in a component.
#[derive(Clone, Copy, Debug)]
pub(crate) struct PlacedCell {
    /// Index of the cell.
    pub cell: usize,
    /// Its centre's lattice position in the component's frame.
    pub centre: Hex,
    /// Rotation ρ: slot j lies along lattice direction (j + ρ) mod 6.
    pub rotation: u8,
}

/// The assembler: cells plus which cells each circle belongs to.
pub(crate) struct Assembler<'a> {
    cells: &'a [Cell],
    /// Cells holding circle i (as centre or neighbour): `holders[start[i]..start[i + 1]]`.
    holders: Vec<u32>,
    start: Vec<u32>,
    /// Rank of each cell (0 = best): full cells first, then by residual.
    rank: Vec<u32>,
    state: Vec<State>,
    /// Component owning each circle, and its position there.
    owner: Vec<Option<(u32, Hex)>>,
    /// The circle at each (component, position).
    taken: HashMap<(u32, Hex), u32>,
}

impl<'a> Assembler<'a> {
    /// Prepare assembly of `cells` over `n_circles` detections.
    pub(crate) fn new(cells: &'a [Cell], n_circles: usize) -> Assembler<'a> {
        let mut start = vec![0u32; n_circles + 1];
        for c in cells {
            for (_, m) in c.members() {
                start[m as usize + 1] += 1;
            }
        }
        for i in 0..n_circles {
            start[i + 1] += start[i];
        }
        let mut fill = start.clone();
        let mut holders = vec![0u32; start[n_circles] as usize];
        for (k, c) in cells.iter().enumerate() {
            for (_, m) in c.members() {
                holders[fill[m as usize] as usize] = k as u32;
                fill[m as usize] += 1;
            }
        }
        let mut order: Vec<usize> = (0..cells.len()).collect();
        order.sort_by(|&a, &b| quality_order(&cells[a], &cells[b]));
        let mut rank = vec![0u32; cells.len()];
        for (r, &k) in order.iter().enumerate() {
            rank[k] = r as u32;
        }
        Assembler {
            cells,
            holders,
            start,
            rank,
            state: vec![State::Pending; cells.len()],
            owner: vec![None; n_circles],
            taken: HashMap::new(),
        }
    }

    /// Cell indices best first.
    pub(crate) fn by_quality(&self) -> Vec<usize> {
        let mut order: Vec<usize> = (0..self.cells.len()).collect();
        order.sort_by_key(|&k| self.rank[k]);
        order
    }

    /// Whether a cell can seed a new component: still pending and none of its circles taken.
    pub(crate) fn can_seed(&self, k: usize) -> bool {
        self.state[k] == State::Pending
            && self.cells[k]
                .members()
                .all(|(_, m)| self.owner[m as usize].is_none())
    }

    /// Grow component number `id` from seed cell `seed`: its centre at the frame origin, its
    /// slot 0 along lattice direction 0.
    pub(crate) fn grow(&mut self, id: u32, seed: usize) -> Component {
        let mut comp = Component::default();
        let mut heap = Queue::new();
        self.commit(id, seed, Hex::new(0, 0), 0, &mut comp, &mut heap);
        while let Some((_, k)) = heap.pop() {
            if self.state[k] != State::Pending {
                continue;
            }
            match self.fit(id, k) {
                Fit::NotReady => {}
                Fit::Conflict => {
                    self.state[k] = State::Rejected;
                    comp.rejected += 1;
                }
                Fit::Place(h, rho) => self.commit(id, k, h, rho, &mut comp, &mut heap),
            }
        }
        comp
    }

    /// Try to place cell `k` in component `id`: its centre position and rotation from the
    /// circles already placed, and a check that every other circle of it agrees or is free.
    fn fit(&self, id: u32, k: usize) -> Fit {
        let c = &self.cells[k];
        // (slot, position) of the circles already placed; slot None is the centre.
        let mut placed = Vec::with_capacity(7);
        for (slot, m) in c.members() {
            match self.owner[m as usize] {
                Some((owner, h)) if owner == id => placed.push((slot, h)),
                Some(_) => return Fit::Conflict,
                None => {}
            }
        }
        if placed.len() < 2 {
            return Fit::NotReady;
        }
        // The first placed circle fixes the centre for each rotation; all others must agree.
        let (s0, h0) = placed[0];
        let Some((centre, rho)) = (0..6).find_map(|rho| {
            let centre = h0 - slot_offset(s0, rho);
            placed
                .iter()
                .all(|&(s, h)| centre + slot_offset(s, rho) == h)
                .then_some((centre, rho))
        }) else {
            return Fit::Conflict;
        };
        // The free circles' positions must not be held by other circles.
        let occupied = |h: Hex, m: u32| self.position_holder(id, h).is_some_and(|other| other != m);
        for (slot, m) in c.members() {
            if self.owner[m as usize].is_none() && occupied(centre + slot_offset(slot, rho), m) {
                return Fit::Conflict;
            }
        }
        Fit::Place(centre, rho as u8)
    }

    /// Circle holding lattice position `h` in component `id`, if any.
    fn position_holder(&self, id: u32, h: Hex) -> Option<u32> {
        self.taken.get(&(id, h)).copied()
    }

    /// Place cell `k` of component `id` with its centre at `centre` and rotation `rho`, label
    /// its free circles, and queue every cell holding a newly labelled circle.
    fn commit(
        &mut self,
        id: u32,
        k: usize,
        centre: Hex,
        rho: u8,
        comp: &mut Component,
        heap: &mut Queue,
    ) {
        self.state[k] = State::Placed;
        comp.cells.push(PlacedCell {
            cell: k,
            centre,
            rotation: rho,
        });
        for (slot, m) in self.cells[k].members() {
            let h = centre + slot_offset(slot, rho as usize);
            if self.owner[m as usize].is_some() {
                continue;
            }
            self.owner[m as usize] = Some((id, h));
            self.taken.insert((id, h), m);
            comp.points.push((m, h));
            let (a, b) = (
                self.start[m as usize] as usize,
                self.start[m as usize + 1] as usize,
            );
            for &holder in &self.holders[a..b] {
                let holder = holder as usize;
                if self.state[holder] == State::Pending {
                    heap.push((Reverse(self.rank[holder]), holder));
                }
            }
        }
    }
}

/// Lattice offset of a cell member from the cell centre: slot j lies along direction
/// (j + ρ) mod 6; the centre (slot `None`) at zero.
fn slot_offset(slot: Option<usize>, rho: usize) -> Hex {
    slot.map_or(Hex::new(0, 0), |j| Hex::DIRECTIONS[(j + rho) % 6])
}

/// Order cells best first: three checked pairs, then full, then by worst normalised residual.
fn quality_order(a: &Cell, b: &Cell) -> std::cmp::Ordering {
    let key = |c: &Cell| (3 - c.pairs, !c.is_full());
    key(a).cmp(&key(b)).then(a.error.total_cmp(&b.error))
}

/// Outcome of trying to place a cell.
enum Fit {
    NotReady,
    Conflict,
    Place(Hex, u8),
}

/// Heap entries: lowest rank first.
type Queue = BinaryHeap<(Reverse<u32>, usize)>;
