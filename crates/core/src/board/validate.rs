//! The rules a board must keep for its codes to decode (docs/design.md §3) and for its geometry
//! to make sense; [`Board::validate`] names the field that breaks one.

use super::{Board, Code, Hex, MarkerKind, Sides};
use crate::limits;
use std::collections::HashMap;

/// A broken rule: the board field to fix (dotted, as in a board file) and what is wrong.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("field `{field}`: {message}")]
pub struct InvalidField {
    /// Dotted field name, e.g. `pitch` or `codes.front_side`.
    pub field: String,
    /// What is wrong with it.
    pub message: String,
}

fn invalid(field: &str, message: String) -> InvalidField {
    InvalidField {
        field: field.to_owned(),
        message,
    }
}

/// Fails unless every number is finite and `ok` holds.
fn check(field: &str, values: &[f64], ok: bool, rule: &str) -> Result<(), InvalidField> {
    if values.iter().all(|v| v.is_finite()) && ok {
        Ok(())
    } else {
        let shown = match values {
            [v] => v.to_string(),
            _ => format!("{values:?}"),
        };
        Err(invalid(field, format!("{shown} breaks the rule {rule}")))
    }
}

impl Board {
    /// Check the board, first broken rule first:
    /// - a double-sided board has every code, `marker_spacing` and `thickness`; a
    ///   single-sided one (`sides = 1`) has no back code, no `thickness` and no `front_back`
    ///   (nothing of a back), and `codes.front_side` with `marker_spacing` or neither;
    /// - `name` not empty; every length finite; `pitch`, `radius`, `half_width`,
    ///   `half_height`, `thickness`, `size` positive; `pitch` > 2·`radius` (circles apart);
    ///   `ring` 0 < inner < outer < 1; the circles (centre ± R) inside `size`;
    ///   `marker_spacing` ≥ 1; `front_back` (any rigid transform) finite;
    /// - each code of weight ≥ 3 and aperiodic (no rotation but the identity maps it to
    ///   itself); any two rotations of different codes at Hamming distance ≥ 2 (so distinct);
    /// - the centre cell wholly on the board (side marks are placed only where they are);
    ///   marker cells disjoint; no circle but a marker centre whose ringed neighbours (as
    ///   printed, a missing neighbour read as unringed) read as a rotation of any code.
    pub fn validate(&self) -> Result<(), InvalidField> {
        self.check_sides()?;
        self.check_geometry()?;
        self.check_codes()?;
        self.check_markers()
    }

    /// What each number of printed sides needs and forbids.
    fn check_sides(&self) -> Result<(), InvalidField> {
        let has = [
            ("codes.back_center", self.codes.back_center.is_some()),
            ("codes.back_side", self.codes.back_side.is_some()),
            ("thickness", self.thickness.is_some()),
            ("front_back", self.front_back.is_some()),
        ];
        match self.sides {
            Sides::Two => {
                let needed = [
                    ("codes.back_center", has[0].1),
                    ("codes.front_side", self.codes.front_side.is_some()),
                    ("codes.back_side", has[1].1),
                    ("marker_spacing", self.marker_spacing.is_some()),
                    ("thickness", has[2].1),
                ];
                match needed.iter().find(|(_, present)| !present) {
                    Some((field, _)) => Err(invalid(
                        field,
                        "missing: a double-sided board needs it (write `sides = 1` for a board \
                         printed on the front only)"
                            .into(),
                    )),
                    None => Ok(()),
                }
            }
            Sides::One => {
                if let Some((field, _)) = has.iter().find(|(_, present)| *present) {
                    return Err(invalid(
                        field,
                        "a single-sided board (sides = 1) has no back: remove it".into(),
                    ));
                }
                match (self.codes.front_side, self.marker_spacing) {
                    (Some(_), None) => Err(invalid(
                        "marker_spacing",
                        "missing: side marks (codes.front_side) need their spacing".into(),
                    )),
                    (None, Some(_)) => Err(invalid(
                        "codes.front_side",
                        "missing: marker_spacing places side marks, which need their code \
                         (or remove marker_spacing)"
                            .into(),
                    )),
                    _ => Ok(()),
                }
            }
        }
    }

    fn check_geometry(&self) -> Result<(), InvalidField> {
        if self.name.trim().is_empty() {
            return Err(invalid("name", "the board needs a name".into()));
        }
        let (d, r) = (self.pitch, self.radius);
        check("radius", &[r], r > 0.0, "radius > 0")?;
        check("pitch", &[d], d > 2.0 * r, "pitch > 2·radius")?;
        let [inner, outer] = self.ring;
        let ring_ok = 0.0 < inner && inner < outer && outer < 1.0;
        check("ring", &self.ring, ring_ok, "0 < inner < outer < 1")?;
        check(
            "half_width",
            &[self.half_width],
            self.half_width > 0.0,
            "half_width > 0",
        )?;
        check(
            "half_height",
            &[self.half_height],
            self.half_height > 0.0,
            "half_height > 0",
        )?;
        self.check_extent()?;
        let [w, h] = self.size;
        let fits = 2.0 * (self.half_width + r) <= w && 2.0 * (self.half_height + r) <= h;
        check(
            "size",
            &self.size,
            fits,
            "width ≥ 2·(half_width + radius), height ≥ 2·(half_height + radius)",
        )?;
        if let Some(t) = self.thickness {
            check("thickness", &[t], t > 0.0, "thickness > 0")?;
        }
        if let Some(s) = self.marker_spacing.filter(|&s| s < 1) {
            return Err(invalid("marker_spacing", format!("{s} must be at least 1")));
        }
        if let Some(t) = &self.front_back {
            check("front_back.rotation", &t.rotation, true, "all finite")?;
            check("front_back.translation", &t.translation, true, "all finite")?;
        }
        Ok(())
    }

    /// The pitch is at least [`limits::MIN_BOARD_PITCH_MM`] and a side has at most
    /// [`limits::MAX_BOARD_CIRCLES`] circles (rows × circles per row, an upper bound known
    /// before any lattice is built).
    fn check_extent(&self) -> Result<(), InvalidField> {
        let d = self.pitch;
        if d < limits::MIN_BOARD_PITCH_MM {
            return Err(invalid(
                "pitch",
                format!(
                    "{d} mm is below the smallest pitch, {} mm",
                    limits::MIN_BOARD_PITCH_MM
                ),
            ));
        }
        let rows = 2.0 * (self.half_height / (d * 0.75f64.sqrt())).floor() + 1.0;
        let per_row = 2.0 * (self.half_width / d).floor() + 1.0;
        if rows * per_row > limits::MAX_BOARD_CIRCLES {
            let field = if rows > per_row {
                "half_height"
            } else {
                "half_width"
            };
            return Err(invalid(
                field,
                format!(
                    "about {:.0} circles per side (pitch {d} mm): at most {}",
                    rows * per_row,
                    limits::MAX_BOARD_CIRCLES
                ),
            ));
        }
        Ok(())
    }

    fn check_codes(&self) -> Result<(), InvalidField> {
        let present: Vec<(MarkerKind, Code)> = self.codes.present().collect();
        for (i, &(a, code)) in present.iter().enumerate() {
            let field = format!("codes.{}", a.name());
            if code.weight() < 3 {
                return Err(invalid(
                    &field,
                    format!(
                        "{code} has {} ringed neighbours, needs at least 3",
                        code.weight()
                    ),
                ));
            }
            if let Some(k) = (1..6).find(|&k| code.rotated(k) == code) {
                return Err(invalid(
                    &field,
                    format!("{code} is periodic: turned by {k} steps it reads the same"),
                ));
            }
            for &(b, other) in &present[..i] {
                for k in 0..6 {
                    let dist = (code.rotated(k).0 ^ other.0).count_ones();
                    if dist < 2 {
                        return Err(invalid(
                            &field,
                            format!(
                                "{code} turned by {k} steps reads {} and is {dist} bit(s) from \
                                 codes.{} = {other}; any two rotations of different codes \
                                 must differ in at least 2 bits",
                                code.rotated(k),
                                b.name()
                            ),
                        ));
                    }
                }
            }
        }
        Ok(())
    }

    fn check_markers(&self) -> Result<(), InvalidField> {
        let origin = Hex::new(0, 0);
        for h in std::iter::once(origin).chain(origin.neighbours()) {
            if !self.contains(h) {
                let p = self.position(h);
                let field = if p.x.abs() > self.half_width {
                    "half_width"
                } else {
                    "half_height"
                };
                return Err(invalid(
                    field,
                    format!(
                        "the centre cell is not wholly on the board: no circle at ({}, {})",
                        h.q, h.r
                    ),
                ));
            }
        }
        for &side in self.sides.list() {
            let cells = self.marker_cells(side);
            let mut owner: HashMap<Hex, Hex> = HashMap::new();
            for cell in &cells {
                for h in std::iter::once(cell.center).chain(cell.center.neighbours()) {
                    if let Some(other) = owner.insert(h, cell.center) {
                        return Err(invalid(
                            "marker_spacing",
                            format!(
                                "with spacing {} the marker cells at ({}, {}) and ({}, {}) of \
                                 the {side} share the circle ({}, {})",
                                self.marker_spacing.unwrap_or(0),
                                other.q,
                                other.r,
                                cell.center.q,
                                cell.center.r,
                                h.q,
                                h.r
                            ),
                        ));
                    }
                }
            }
            let ringed = self.ringed(side);
            for h in self.lattice() {
                if owner.get(&h) == Some(&h) {
                    continue; // a marker centre
                }
                let read = Code(
                    (0..6)
                        .map(|k| u8::from(ringed.contains(&h.neighbour(k))) << k)
                        .sum(),
                );
                if let Some((kind, k)) = self.codes.decode(read) {
                    return Err(invalid(
                        "marker_spacing",
                        format!(
                            "with spacing {} the circle ({}, {}) of the {side}, no marker \
                             centre, has rings of two marker cells around it that read {read}, \
                             codes.{} turned by {k} steps",
                            self.marker_spacing.unwrap_or(0),
                            h.q,
                            h.r,
                            kind.name()
                        ),
                    ));
                }
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::board::file::BoardError;

    const HEX600: &str = include_str!("../../../../rigs/boards/hex600.toml");

    #[test]
    fn hex600_is_valid() {
        assert_eq!(Board::hex600().validate(), Ok(()));
    }

    /// The shipped hex600 file with `key = …` replaced by `line` (or `line` appended when
    /// no such key is written), read as a board file; the error must name `field`.
    fn rejects(key: &str, line: &str, field: &str) -> String {
        let prefix = format!("{key} =");
        let mut text: String = HEX600
            .lines()
            .map(|l| if l.starts_with(&prefix) { line } else { l })
            .collect::<Vec<_>>()
            .join("\n");
        if !HEX600.lines().any(|l| l.starts_with(&prefix)) {
            text = format!("{text}\n{line}\n");
        }
        let e = Board::from_toml_str(&text).expect_err(line);
        assert!(matches!(e, BoardError::Invalid { .. }), "{line}: {e}");
        assert_eq!(e.field(), Some(field), "{line}: {e}");
        assert!(e.line().is_some(), "{line}: {e}");
        e.to_string()
    }

    #[test]
    fn one_failing_file_per_rule() {
        rejects("name", "name = \"  \"", "name");
        rejects("radius", "radius = -1.0", "radius");
        rejects("radius", "radius = nan", "radius");
        rejects("pitch", "pitch = 12.0", "pitch");
        rejects("pitch", "pitch = inf", "pitch");
        rejects("ring", "ring = [0.75, 0.45]", "ring");
        rejects("ring", "ring = [0.0, 0.75]", "ring");
        rejects("ring", "ring = [0.45, 1.0]", "ring");
        rejects("half_width", "half_width = 0.0", "half_width");
        rejects("half_height", "half_height = -3.0", "half_height");
        rejects("size", "size = [590.0, 500.0]", "size");
        rejects("size", "size = [600.0, 470.0]", "size");
        rejects("thickness", "thickness = 0.0", "thickness");
        rejects("marker_spacing", "marker_spacing = 0", "marker_spacing");
    }

    #[test]
    fn side_transform_must_be_finite() {
        let measured =
            "\n[front_back]\nrotation = [0.0, 3.14, 0.0]\ntranslation = [0.0, 0.0, -10.0]\n";
        let ok = format!("{HEX600}{measured}");
        assert!(Board::from_toml_str(&ok).is_ok());
        for (bad, field) in [
            ("rotation = [0.0, nan, 0.0]", "front_back.rotation"),
            ("translation = [0.0, 0.0, inf]", "front_back.translation"),
        ] {
            let key = bad.split(' ').next().unwrap();
            let text = ok.replace(ok.lines().find(|l| l.starts_with(key)).unwrap(), bad);
            let e = Board::from_toml_str(&text).unwrap_err();
            assert_eq!(e.field(), Some(field), "{e}");
            let line = text.lines().position(|l| l == bad).unwrap() + 1;
            assert_eq!(e.line(), Some(line), "{e}");
        }
    }

    #[test]
    fn code_rules() {
        // Weight 2.
        rejects("front_side", "front_side = \"001001\"", "codes.front_side");
        // Periodic: 010101 turned by 2 steps reads the same (weight 3 passes).
        let msg = rejects(
            "back_center",
            "back_center = \"010101\"",
            "codes.back_center",
        );
        assert!(msg.contains("periodic"), "{msg}");
        // A rotation of another code: 010110 is front_side 001011 turned by 1 step. A pair
        // is reported on the later code in MarkerKind::ALL, naming the earlier one.
        let msg = rejects("back_side", "back_side = \"010110\"", "codes.back_side");
        assert!(msg.contains("0 bit(s) from codes.front_side"), "{msg}");
        // One bit from a rotation of another code: 001111 vs front_center's 011111.
        let msg = rejects(
            "back_center",
            "back_center = \"001111\"",
            "codes.back_center",
        );
        assert!(msg.contains("1 bit(s) from codes.front_center"), "{msg}");
    }

    #[test]
    fn marker_rules() {
        // The centre cell needs circles at (±1, 0): half_width below the pitch drops them.
        let b = Board {
            half_width: 15.0,
            size: [50.0, 500.0],
            ..Board::hex600()
        };
        assert_eq!(b.validate().unwrap_err().field, "half_width");
        // … and at (0, ±1), (±1, ∓1), √3/2·d = 17.3 mm from the x axis.
        let b = Board {
            half_height: 17.0,
            size: [600.0, 50.0],
            ..Board::hex600()
        };
        assert_eq!(b.validate().unwrap_err().field, "half_height");
        // Spacing 2: cells share circles.
        let msg = rejects("marker_spacing", "marker_spacing = 2", "marker_spacing");
        assert!(msg.contains("share"), "{msg}");
        // Spacing 3: cells apart, but circles between them see rings of two cells.
        let msg = rejects("marker_spacing", "marker_spacing = 3", "marker_spacing");
        assert!(
            msg.contains("no marker centre, has rings of two marker cells"),
            "{msg}"
        );
    }

    /// docs/design.md §3: with spacing 6 any non-marker circle has at most 2 ringed neighbours.
    #[test]
    fn hex600_non_marker_circles_see_at_most_two_rings() {
        let b = Board::hex600();
        for side in crate::board::Side::BOTH {
            let ringed = b.ringed(side);
            let centres: Vec<Hex> = b.marker_cells(side).iter().map(|c| c.center).collect();
            let most = b
                .lattice()
                .into_iter()
                .filter(|h| !centres.contains(h))
                .map(|h| h.neighbours().iter().filter(|n| ringed.contains(n)).count())
                .max();
            assert_eq!(most, Some(2), "{side}");
        }
    }
}
