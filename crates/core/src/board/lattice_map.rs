//! Maps between lattice frames, and their estimate from labelled pairs by voting.
//!
//! A view's lattice labels may sit in a frame of their own (a component of the grid, an
//! unanchored view); a [`LatticeMap`] takes them into another (the board side's, another
//! component's): h ↦ rotate(h, rotation) + offset. Each pair (label, position in the other
//! frame) is consistent with one map per rotation; [`lattice_votes`] counts them, and the map most
//! pairs agree on is the estimate (each caller decides how clear a majority it needs).

use super::Hex;
use std::collections::HashMap;
use std::hash::Hash;

/// A map from one lattice frame into another: h ↦ rotate(h, `rotation`) + `offset`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct LatticeMap {
    /// 60° counter-clockwise steps (0–5).
    pub rotation: u8,
    /// Translation applied after the rotation.
    pub offset: Hex,
}

impl LatticeMap {
    /// The map that leaves every label where it is.
    pub const IDENTITY: LatticeMap = LatticeMap {
        rotation: 0,
        offset: Hex { q: 0, r: 0 },
    };

    /// Apply the map.
    pub fn apply(self, h: Hex) -> Hex {
        h.rotate(self.rotation as usize) + self.offset
    }

    /// The map back.
    pub fn inverse(self) -> LatticeMap {
        let rotation = (6 - self.rotation % 6) % 6;
        LatticeMap {
            rotation,
            offset: -self.offset.rotate(rotation as usize),
        }
    }

    /// This map, then `outer`.
    pub fn then(self, outer: LatticeMap) -> LatticeMap {
        LatticeMap {
            rotation: (self.rotation + outer.rotation) % 6,
            offset: outer.apply(self.offset),
        }
    }

    /// The six maps, one per rotation, that take `from` onto `to`.
    pub fn onto(from: Hex, to: Hex) -> impl Iterator<Item = LatticeMap> {
        (0..6u8).map(move |rotation| LatticeMap {
            rotation,
            offset: to - from.rotate(rotation as usize),
        })
    }
}

/// Votes of labelled pairs for maps: each `(key, from, to)` votes for the six maps
/// ([`LatticeMap::onto`]) under its key (e.g. the board side `to` lies on).
pub fn lattice_votes<K: Hash + Eq + Copy>(
    pairs: impl IntoIterator<Item = (K, Hex, Hex)>,
) -> HashMap<(K, LatticeMap), usize> {
    let mut votes = HashMap::new();
    for (key, from, to) in pairs {
        for map in LatticeMap::onto(from, to) {
            *votes.entry((key, map)).or_default() += 1;
        }
    }
    votes
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn maps_invert_compose_and_are_found_by_their_pairs() {
        let m = LatticeMap {
            rotation: 2,
            offset: Hex::new(3, -1),
        };
        let hs = [
            Hex::new(0, 0),
            Hex::new(2, -5),
            Hex::new(-4, 1),
            Hex::new(7, 3),
        ];
        for h in hs {
            assert_eq!(m.inverse().apply(m.apply(h)), h);
            let n = LatticeMap {
                rotation: 5,
                offset: Hex::new(-2, 4),
            };
            assert_eq!(m.then(n).apply(h), n.apply(m.apply(h)));
        }
        assert_eq!(m.then(m.inverse()), LatticeMap::IDENTITY);
        // Every pair votes for the true map; the other rotations scatter.
        let v = lattice_votes(hs.iter().map(|&h| ((), h, m.apply(h))));
        let (best, n) = v.iter().max_by_key(|(_, &n)| n).unwrap();
        assert_eq!((best.1, *n), (m, hs.len()));
        assert!(v.values().filter(|&&c| c == hs.len()).count() == 1);
    }
}
