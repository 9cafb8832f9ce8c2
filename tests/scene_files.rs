//! Every scene file shipped in rigs/scenes loads and shows the board side it says.

use hexcal::board::Side;
use hexcal::sim::{ground_truth, Scene};

#[test]
fn shipped_scenes_load_and_see_the_board() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("rigs/scenes");
    let mut n = 0;
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_none_or(|e| e != "toml") {
            continue;
        }
        let scene = Scene::load(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        let truth = ground_truth(&scene).unwrap();
        let name = path.file_name().unwrap().to_string_lossy();
        let expect = if name.starts_with("back") {
            Side::Back
        } else {
            Side::Front
        };
        assert_eq!(truth.side, Some(expect), "{name}");
        let whole = truth.circles.iter().filter(|c| c.whole).count();
        assert!(whole > 200, "{name}: {whole} whole circles");
        assert!(
            whole < truth.circles.len(),
            "{name}: meant to be partly out of frame"
        );
        n += 1;
    }
    assert!(n > 0);
}
