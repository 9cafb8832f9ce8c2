//! `hexcal bench calib`: one bundle adjustment of a synthetic rig, its time, peak memory
//! and accuracy against the truth; and the process figures the harnesses print.

use crate::calib::synthetic::{run_case, Case, Start};

/// `hexcal bench calib`: one adjustment of a synthetic rig, its time, peak memory and
/// accuracy.
pub fn bench_calib(
    cameras: usize,
    projectors: usize,
    poses: usize,
    sigma: f64,
    seed: u64,
    real_start: bool,
) -> Result<String, crate::calib::CalibError> {
    let case = Case {
        cameras,
        projectors,
        poses,
        sigma,
        seed,
        start: if real_start {
            Start::Real
        } else {
            Start::Perturbed
        },
    };
    let b = run_case(&case)?;
    let mut out = String::new();
    out += &format!(
        "bundle adjustment: {} devices ({} excluded), {poses} poses, {} observations, n = {}, p = {}, {} threads, {:?} start",
        b.devices,
        b.excluded,
        b.observations,
        b.dof.0,
        b.dof.1,
        rayon::current_num_threads(),
        case.start,
    );
    out.push('\n');
    out += &format!(
        "{:.3} s wall, {} CPU, peak memory {}, {} LM iterations (+ {} coarse){}; posterior σ {:.4} px \
         (simulated {sigma}), worst focal error {:.4} %, worst parameter {:.2} σ ({}; bound \
         {:.2}): {}",
        b.seconds,
        cpu_seconds().map_or("unknown".into(), |s| format!("{s:.2} s")),
        peak_memory().map_or("unknown".into(), |kb| format!(
            "{:.1} MiB",
            kb as f64 / 1024.0
        )),
        b.iterations,
        b.coarse_iterations,
        if b.converged { "" } else { " (not converged)" },
        b.posterior_sigma,
        100.0 * b.worst_focal_error,
        b.worst_z.0,
        b.worst_z.1,
        b.z_bound,
        if b.passes(sigma) { "pass" } else { "FAIL" },
    );
    out.push('\n');
    Ok(out)
}

/// CPU time of the process so far (user + system, s, from /proc/self/stat at 100 ticks per
/// second): on a shared machine a steadier figure than the wall time.
pub fn cpu_seconds() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    // Fields after the command name (in parentheses): utime and stime are the 12th and 13th.
    let rest = stat.rsplit_once(')')?.1;
    let f: Vec<&str> = rest.split_whitespace().collect();
    let ticks: f64 = f.get(11)?.parse::<f64>().ok()? + f.get(12)?.parse::<f64>().ok()?;
    Some(ticks / 100.0)
}

/// The process's peak resident memory (kB, `VmHWM` of /proc/self/status), where known.
pub fn peak_memory() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    line.split_whitespace().nth(1)?.parse().ok()
}
