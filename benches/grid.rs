//! Grid-building speed on the six sample images, from their true ellipses (the detector's
//! share of the 80 ms detect + grid budget is not part of this). Prints per-image timings.
//!
//! Run: `cargo bench --bench grid`.

#[path = "../tests/support/grid_truth.rs"]
mod truth;

use hexcal::board::Board;
use hexcal::grid::{build, GridParams};
use std::time::Instant;

fn main() {
    let board = Board::hex600();
    let params = GridParams::default();
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    println!("grid::build, single thread ({threads} cores on this machine, shared)");
    println!(
        "{:<16} {:>7} {:>9} {:>10} {:>10}",
        "image", "circles", "labelled", "median ms", "min ms"
    );
    for name in truth::SAMPLES {
        let s = truth::load(name);
        let circles = truth::true_detections(&s);
        let mut times = Vec::new();
        let mut labelled = 0;
        for _ in 0..200 {
            let t0 = Instant::now();
            let grid = build(&s.image, &circles, &board, &params);
            times.push(t0.elapsed().as_secs_f64() * 1e3);
            labelled = grid.points.len();
        }
        times.sort_by(f64::total_cmp);
        println!(
            "{name:<16} {:>7} {labelled:>9} {:>10.3} {:>10.3}",
            circles.len(),
            times[times.len() / 2],
            times[0]
        );
    }
}
