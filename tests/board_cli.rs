//! `hexcal board`: the written file is the library's SVG, written whole (no temporary file
//! left beside it), and bad input fails with a message naming what is wrong.

use hexcal::board::{Board, Side};

#[path = "support/cli.rs"]
mod cli;
use cli::{hexcal, scratch};

#[test]
fn board_writes_each_side() {
    let dir = scratch("board-cli");
    let file = concat!(env!("CARGO_MANIFEST_DIR"), "/rigs/boards/hex600.toml");
    for (side, board) in [(Side::Front, "hex600"), (Side::Back, file)] {
        let out = dir.join(format!("{side}.svg"));
        let run = hexcal(&[
            "board",
            "--board",
            board,
            "--side",
            side.name(),
            "--out",
            out.to_str().unwrap(),
        ]);
        assert!(run.status.success(), "{run:?}");
        assert_eq!(
            std::fs::read_to_string(&out).unwrap(),
            Board::hex600().svg(side)
        );
    }
    let mut names: Vec<_> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .collect();
    names.sort();
    assert_eq!(names, ["back.svg", "front.svg"]);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn board_rejects_bad_input() {
    let dir = scratch("board-cli-bad");
    let bad = dir.join("bad.toml");
    let text = include_str!("../rigs/boards/hex600.toml").replace("pitch = 20.0", "pitch = 12.0");
    std::fs::write(&bad, text).unwrap();
    let out = dir.join("x.svg");
    let out = out.to_str().unwrap();
    for (args, says) in [
        (
            vec!["--board", bad.to_str().unwrap(), "--side", "front"],
            "field `pitch`",
        ),
        (vec!["--board", "hex700", "--side", "front"], "hex700"),
        (vec!["--side", "top"], "top"),
    ] {
        let run = hexcal(&[&["board", "--out", out][..], &args].concat());
        let err = String::from_utf8_lossy(&run.stderr);
        assert!(
            !run.status.success() && err.contains(says),
            "{args:?}: {err}"
        );
    }
    let run = hexcal(&[
        "board",
        "--side",
        "front",
        "--out",
        dir.join("x.pdf").to_str().unwrap(),
    ]);
    assert!(String::from_utf8_lossy(&run.stderr).contains("only SVG"));
    assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 1, "only bad.toml");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A single-sided board draws its front without `--side` and refuses the back in one line
/// naming the board file; a double-sided board needs `--side`.
#[test]
fn board_follows_a_single_sided_board() {
    let dir = scratch("board-cli-one-side");
    let file = concat!(env!("CARGO_MANIFEST_DIR"), "/rigs/boards/hex600-front.toml");
    let out = dir.join("front.svg");
    let out = out.to_str().unwrap();
    let run = hexcal(&["board", "--board", file, "--out", out]);
    assert!(run.status.success(), "{run:?}");
    let stdout = String::from_utf8_lossy(&run.stdout);
    assert!(
        stdout.contains("hex600-front front side written"),
        "{stdout}"
    );
    let board = Board::load(file).unwrap();
    assert_eq!(
        std::fs::read_to_string(out).unwrap(),
        board.svg(Side::Front)
    );
    for (args, says) in [
        (
            vec!["--board", file, "--side", "back"],
            format!("board {file} is single-sided (sides = 1): it has no back to draw"),
        ),
        (
            vec!["--board", "hex600"],
            "board hex600 has two sides: give --side front or --side back".to_owned(),
        ),
    ] {
        let bad = dir.join("bad.svg");
        let run = hexcal(&[&["board", "--out", bad.to_str().unwrap()][..], &args].concat());
        let err = String::from_utf8_lossy(&run.stderr);
        assert!(!run.status.success(), "{args:?}: {err}");
        assert_eq!(err.trim().lines().count(), 1, "{args:?}: {err}");
        assert!(err.contains(&says), "{args:?}: {err}");
        assert!(!bad.exists(), "{args:?}");
    }
    std::fs::remove_dir_all(&dir).unwrap();
}
