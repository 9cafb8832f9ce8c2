//! Capture scripts and positioners of a rig file (docs/rig-file.md, "Scripts and
//! positioners").
//!
//! Takes the `[[positioner]]` and `[[script]]` tables of a [`RigFile`]; gives them checked —
//! every refusal a [`ValidationError`] (dotted key, message) that the rig-file loader
//! places at `file:line: key: message` — and the script unrolled into a flat [`Plan`]: one
//! [`PlannedStep`] per capture, wait, prompt and move, with `repeat` blocks expanded (their
//! stepping variables substituted) and `every` blocks turned into timed captures, each with
//! its planned start and duration.

use super::file::RigFile;
use hexcal_core::limits;
use hexcal_core::{Invalid, ValidationError};
use regex::Regex;
use serde::Serialize;
use std::collections::{BTreeMap, HashSet};

mod exposure;
pub use super::file::steps::*;
pub use exposure::{Exposure, PoseExposures};

/// Steps an unrolled script may have.
pub const MAX_SCRIPT_STEPS: usize = 100_000;
/// Nesting of `repeat` blocks.
pub const MAX_SCRIPT_DEPTH: usize = 8;
/// Bytes of a prompt, label, command or pattern.
const MAX_SCRIPT_TEXT: usize = 4096;

/// What one unrolled step does.
#[derive(Clone, Debug, PartialEq, Serialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Action {
    /// Capture pose `pose`.
    Capture {
        /// Pose index (captures in script order).
        pose: usize,
        /// Label.
        label: String,
        /// Its tick when the capture belongs to an `every` block.
        #[serde(skip_serializing_if = "Option::is_none")]
        tick: Option<Tick>,
        /// Its own exposure and gain, when the step sets them.
        #[serde(skip_serializing_if = "Option::is_none")]
        exposure: Option<Exposure>,
    },
    /// Wait.
    Wait {
        /// Seconds.
        seconds: f64,
    },
    /// Wait for the operator.
    Prompt {
        /// What to tell the operator.
        text: String,
        /// Longest wait (s); none waits for ever.
        timeout_s: Option<f64>,
    },
    /// Move a positioner.
    Move {
        /// Positioner name.
        positioner: String,
        /// The command line (template filled in).
        command: String,
        /// Pattern of the reply that says done.
        expect: String,
        /// Longest wait for it (s).
        timeout_s: f64,
        /// The template's values.
        to: BTreeMap<String, String>,
    },
}

/// A capture's place in an `every` block: due `index · period_s` after the block began.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Tick {
    /// Which `every` block (0, 1, … in script order).
    pub group: usize,
    /// Capture number in the block.
    pub index: u32,
    /// Seconds between captures.
    pub period_s: f64,
    /// Countdown before each capture (s).
    pub countdown_s: f64,
}

/// One unrolled step with its planned times.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct PlannedStep {
    /// Where it is written, e.g. `script[2].steps[0]`, and its round in repeats.
    pub step: String,
    /// What it does.
    #[serde(flatten)]
    pub action: Action,
    /// Planned start after the script began (s).
    pub planned_start_s: f64,
    /// Planned duration (s); an operator's prompt without timeout is planned at 0.
    pub planned_s: f64,
}

/// A script unrolled.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct Plan {
    /// Steps in order.
    pub steps: Vec<PlannedStep>,
    /// Captures (poses) in all.
    pub captures: usize,
    /// Planned duration (s).
    pub duration_s: f64,
}

/// Unrolls scripts: variables in scope, planned clock, poses and blocks so far.
struct Unroller<'a> {
    rig: &'a RigFile,
    capture_s: f64,
    clock: f64,
    poses: usize,
    groups: usize,
    /// Planned axes of each simulated stage (angle, tilt), for its move times.
    axes: BTreeMap<String, (f64, f64)>,
    out: Vec<PlannedStep>,
}

impl RigFile {
    /// The script unrolled, a capture planned at `capture_s` seconds (its frames and the
    /// pose pause). `None` when the rig file has no script.
    pub fn script_plan(&self, capture_s: f64) -> Result<Option<Plan>, ValidationError> {
        if self.script.is_empty() {
            return Ok(None);
        }
        let mut u = Unroller {
            rig: self,
            capture_s,
            clock: 0.0,
            poses: 0,
            groups: 0,
            axes: BTreeMap::new(),
            out: Vec::new(),
        };
        u.block(&self.script, "script", &BTreeMap::new(), "", 0)?;
        Ok(Some(Plan {
            captures: u.poses,
            duration_s: u.clock,
            steps: u.out,
        }))
    }

    /// The positioner named `name`.
    pub fn positioner(&self, name: &str) -> Option<&PositionerSpec> {
        self.positioners.iter().find(|p| p.name == name)
    }

    /// `[[positioner]]` and `[[script]]`: positioners well formed with unique names, the
    /// script unrolls, and a simulated rig without a simulated stage has a board pose for
    /// every capture.
    pub(super) fn check_script(&self, simulated: bool) -> Result<(), ValidationError> {
        let mut names = HashSet::new();
        for (i, p) in self.positioners.iter().enumerate() {
            let at = |k: &str| format!("positioner[{i}].{k}");
            limits::device_name(&p.name).map_err(|m| m.at(at("name")))?;
            if !names.insert(p.name.as_str()) {
                return Err(ValidationError::new(
                    at("name"),
                    format!("{:?} names two positioners", p.name),
                ));
            }
            check_positioner(p, &at)?;
        }
        let Some(plan) = self.script_plan(0.0)? else {
            return Ok(());
        };
        if plan.captures == 0 {
            return Err(ValidationError::new(
                "script",
                "a script needs at least one capture",
            ));
        }
        limits::count(plan.captures, limits::MAX_POSES, "captures").map_err(|m| m.at("script"))?;
        let staged = self
            .positioners
            .iter()
            .any(|p| p.driver == PositionerDriver::Sim);
        let poses = self.poses.as_ref().map_or(0, |p| p.count);
        if simulated && !staged && poses < plan.captures {
            return Err(ValidationError::new(
                "poses.count",
                format!(
                    "the script captures {} poses but the simulated rig has {poses} board \
                     poses and no sim positioner to move the board",
                    plan.captures
                ),
            ));
        }
        Ok(())
    }

    /// Whether a simulated stage places the board (then `[poses]` is not needed).
    pub fn has_sim_stage(&self) -> bool {
        self.positioners
            .iter()
            .any(|p| p.driver == PositionerDriver::Sim)
    }
}

/// One positioner: its driver's keys, durations, patterns and template.
fn check_positioner(
    p: &PositionerSpec,
    at: &dyn Fn(&str) -> String,
) -> Result<(), ValidationError> {
    match (p.driver, &p.port, &p.sim) {
        (PositionerDriver::Serial, None, _) => {
            return Err(ValidationError::new(
                at("port"),
                "a serial positioner needs a port",
            ))
        }
        (PositionerDriver::Serial, _, Some(_)) => {
            return Err(ValidationError::new(
                at("sim"),
                "only sim positioners have a sim stage",
            ))
        }
        (PositionerDriver::Sim, Some(_), _) => {
            return Err(ValidationError::new(
                at("port"),
                "a sim positioner has no port",
            ))
        }
        _ => {}
    }
    if p.baud == 0 {
        return Err(ValidationError::new(at("baud"), "0 baud"));
    }
    if !(p.timeout_s > 0.0 && p.timeout_s <= limits::MAX_DURATION_MS / 1e3) {
        return Err(ValidationError::new(
            at("timeout_s"),
            duration_message(p.timeout_s),
        ));
    }
    limits::non_negative(p.move_s, limits::MAX_DURATION_MS / 1e3)
        .map_err(|m| ValidationError::new(at("move_s"), format!("{m} s")))?;
    for (key, text) in [
        ("command", &p.command),
        ("reply", &p.reply),
        ("fault", &p.fault),
    ] {
        check_text(text).map_err(|m| m.at(at(key)))?;
    }
    for (key, pattern) in [("reply", &p.reply), ("fault", &p.fault)] {
        Regex::new(pattern).map_err(|e| ValidationError::new(at(key), pattern_message(&e)))?;
    }
    if p.command.trim().is_empty() {
        return Err(ValidationError::new(at("command"), "an empty command"));
    }
    placeholders(&p.command).map_err(|m| m.at(at("command")))?;
    if let Some(s) = &p.sim {
        check_stage(s, at)?;
    }
    check_protocol(p, at)
}

/// A positioner's protocol and serial settings: patterns that compile, a poll period and a
/// step scale within their ranges, 7 or 8 data bits, 1 or 2 stop bits.
fn check_protocol(p: &PositionerSpec, at: &dyn Fn(&str) -> String) -> Result<(), ValidationError> {
    let mut patterns: Vec<(&str, &str)> = Vec::new();
    if let Some(a) = &p.ack {
        patterns.push(("ack", a));
    }
    if let Some(q) = &p.poll {
        check_text(&q.query).map_err(|m| m.at(at("poll.query")))?;
        if q.query.trim().is_empty() {
            return Err(ValidationError::new(at("poll.query"), "an empty query"));
        }
        patterns.push(("poll.idle", &q.idle));
        if !(q.period_s >= 0.001 && q.period_s <= 60.0) {
            return Err(ValidationError::new(
                at("poll.period_s"),
                format!("{} s is not a poll period (0.001–60 s)", q.period_s),
            ));
        }
    }
    for (key, pattern) in patterns {
        check_text(pattern).map_err(|m| m.at(at(key)))?;
        Regex::new(pattern).map_err(|e| ValidationError::new(at(key), pattern_message(&e)))?;
    }
    if !matches!(p.data_bits, 7 | 8) {
        return Err(ValidationError::new(
            at("data_bits"),
            format!("{}: 7 or 8", p.data_bits),
        ));
    }
    if !matches!(p.stop_bits, 1 | 2) {
        return Err(ValidationError::new(
            at("stop_bits"),
            format!("{}: 1 or 2", p.stop_bits),
        ));
    }
    if let Some(k) = p.steps_per_unit {
        if !(k.is_finite() && k > 0.0 && k <= 1e9) {
            return Err(ValidationError::new(
                at("steps_per_unit"),
                format!("{k}: a scale above 0 and at most 10⁹"),
            ));
        }
    }
    Ok(())
}

fn check_stage(s: &SimStageSpec, at: &dyn Fn(&str) -> String) -> Result<(), ValidationError> {
    let far = limits::MAX_DISTANCE_MM;
    for (key, point) in [("sim.centre", s.centre), ("sim.offset", s.offset)] {
        for v in point {
            limits::within(v, -far, far).map_err(|m| m.at(at(key)))?;
        }
    }
    limits::within(s.roll_deg, -360.0, 360.0).map_err(|m| m.at(at("sim.roll_deg")))?;
    if !(s.speed_deg_s > 0.0 && s.speed_deg_s <= 1e4) {
        return Err(ValidationError::new(
            at("sim.speed_deg_s"),
            format!("{} is not a speed in (0, 10000] deg/s", s.speed_deg_s),
        ));
    }
    if !(s.tilt_limit_deg > 0.0 && s.tilt_limit_deg <= 90.0) {
        return Err(ValidationError::new(
            at("sim.tilt_limit_deg"),
            format!("{} is not in (0, 90] deg", s.tilt_limit_deg),
        ));
    }
    Ok(())
}

fn duration_message(v: f64) -> String {
    format!(
        "{v} is not a duration in (0, {}] s",
        limits::MAX_DURATION_MS / 1e3
    )
}

fn pattern_message(e: &regex::Error) -> String {
    let text = e.to_string();
    let last = text.lines().last().unwrap_or("").trim().to_string();
    format!("not a regular expression: {last}")
}

fn check_text(text: &str) -> Result<(), Invalid> {
    if text.len() > MAX_SCRIPT_TEXT {
        return Err(Invalid(format!(
            "{} bytes of text: at most {MAX_SCRIPT_TEXT}",
            text.len()
        )));
    }
    Ok(())
}

/// The `{name}` placeholders of a template, in order; `{{` and `}}` are literal braces.
pub fn placeholders(template: &str) -> Result<Vec<String>, Invalid> {
    let mut names = Vec::new();
    fill(template, &mut |name| {
        names.push(name.to_string());
        Some(String::new())
    })?;
    Ok(names)
}

/// `template` with every `{name}` replaced by `value(name)`; `Err` names an unknown
/// placeholder or an unclosed brace.
pub fn fill(
    template: &str,
    value: &mut dyn FnMut(&str) -> Option<String>,
) -> Result<String, Invalid> {
    let mut out = String::new();
    let mut rest = template;
    while let Some(i) = rest.find(['{', '}']) {
        out.push_str(&rest[..i]);
        let (c, after) = (rest.as_bytes()[i], &rest[i + 1..]);
        if after.as_bytes().first() == Some(&c) {
            out.push(c as char);
            rest = &after[1..];
            continue;
        }
        if c == b'}' {
            return Err(Invalid(format!("a lone }} in {template:?}")));
        }
        let end = after
            .find('}')
            .ok_or_else(|| Invalid(format!("an unclosed {{ in {template:?}")))?;
        let name = after[..end].trim();
        out.push_str(&value(name).ok_or_else(|| Invalid(format!("{{{name}}} is not defined")))?);
        rest = &after[end + 1..];
    }
    out.push_str(rest);
    Ok(out)
}

/// A number as a command or label shows it: integers without decimals, others with up to
/// six.
pub fn format_number(v: f64) -> String {
    if v == v.trunc() && v.abs() < 1e15 {
        return format!("{v:.0}");
    }
    let s = format!("{v:.6}");
    s.trim_end_matches('0').trim_end_matches('.').to_string()
}

type Vars = BTreeMap<String, f64>;

impl Unroller<'_> {
    /// The steps of one block at `path` (e.g. `script` or `script[2].steps`) under `vars`;
    /// `round` names the repeat rounds around it.
    fn block(
        &mut self,
        steps: &[StepSpec],
        path: &str,
        vars: &Vars,
        round: &str,
        depth: usize,
    ) -> Result<(), ValidationError> {
        if depth > MAX_SCRIPT_DEPTH {
            return Err(ValidationError::new(
                path,
                format!("repeats nested deeper than {MAX_SCRIPT_DEPTH}"),
            ));
        }
        for (i, s) in steps.iter().enumerate() {
            let at = format!("{path}[{i}]");
            self.step(s, &at, vars, round, depth)?;
            if self.out.len() > MAX_SCRIPT_STEPS {
                return Err(ValidationError::new(
                    at,
                    format!("the script unrolls to more than {MAX_SCRIPT_STEPS} steps"),
                ));
            }
        }
        Ok(())
    }

    fn step(
        &mut self,
        s: &StepSpec,
        at: &str,
        vars: &Vars,
        round: &str,
        depth: usize,
    ) -> Result<(), ValidationError> {
        let key = |k: &str| format!("{at}.{k}");
        let kind = step_kind(s).map_err(|m| m.at(at.to_string()))?;
        check_keys(s, kind).map_err(|e| e.map_at(|k| key(k)))?;
        let name = format!("{at}{round}");
        let text = |k: &str, t: &str| -> Result<String, ValidationError> {
            check_text(t).map_err(|m| m.at(key(k)))?;
            fill(t, &mut |n| vars.get(n).map(|&v| format_number(v))).map_err(|m| m.at(key(k)))
        };
        match kind {
            "capture" => {
                let label = text("capture", s.capture.as_deref().unwrap_or(""))?;
                let exposure = self.exposure(s, at)?;
                self.capture(name, label, None, exposure);
            }
            "wait" => {
                let seconds = s.wait.unwrap_or(0.0);
                limits::non_negative(seconds, limits::MAX_DURATION_MS / 1e3)
                    .map_err(|m| ValidationError::new(key("wait"), format!("{m} s")))?;
                self.push(name, Action::Wait { seconds }, seconds);
            }
            "prompt" => {
                let text = text("prompt", s.prompt.as_deref().unwrap_or(""))?;
                let timeout_s = s.timeout_s;
                if let Some(t) = timeout_s.filter(|&t| !(t > 0.0 && t <= 3.6e3)) {
                    return Err(ValidationError::new(key("timeout_s"), duration_message(t)));
                }
                let planned = timeout_s.unwrap_or(0.0);
                self.push(name, Action::Prompt { text, timeout_s }, planned);
            }
            "move" => self.move_step(s, at, &name, vars)?,
            "repeat" => self.repeat(s, at, vars, round, depth)?,
            _ => self.every(s, at, &name, vars)?,
        }
        Ok(())
    }

    fn push(&mut self, step: String, action: Action, planned_s: f64) {
        self.out.push(PlannedStep {
            step,
            action,
            planned_start_s: self.clock,
            planned_s,
        });
        self.clock += planned_s;
    }

    fn capture(
        &mut self,
        step: String,
        label: String,
        tick: Option<Tick>,
        exposure: Option<Exposure>,
    ) {
        let pose = self.poses;
        self.poses += 1;
        let planned = match tick {
            Some(t) => t.period_s.max(self.capture_s),
            None => self.capture_s,
        };
        let action = Action::Capture {
            pose,
            label,
            tick,
            exposure,
        };
        self.push(step, action, planned);
    }

    fn move_step(
        &mut self,
        s: &StepSpec,
        at: &str,
        name: &str,
        vars: &Vars,
    ) -> Result<(), ValidationError> {
        let key = |k: &str| format!("{at}.{k}");
        let positioner = s.move_to.clone().unwrap_or_default();
        let p = self.rig.positioner(&positioner).ok_or_else(|| {
            ValidationError::new(
                key("move"),
                format!("no positioner is named {positioner:?}"),
            )
        })?;
        let given = s.to.clone().unwrap_or_default();
        let mut to = BTreeMap::new();
        for (k, v) in &given {
            let scaled = |x: f64| match p.steps_per_unit {
                Some(k) => format_number((x * k).round()),
                None => format_number(x),
            };
            let value = match v {
                ValueSpec::Number(x) if x.is_finite() => scaled(*x),
                ValueSpec::Number(x) => {
                    return Err(ValidationError::new(
                        key(&format!("to.{k}")),
                        format!("{x}"),
                    ))
                }
                ValueSpec::Text(t) => {
                    check_text(t).map_err(|m| m.at(key(&format!("to.{k}"))))?;
                    let text = fill(t, &mut |n| vars.get(n).map(|&v| format_number(v)))
                        .map_err(|m| m.at(key(&format!("to.{k}"))))?;
                    // A number after substitution is scaled like a number given as such.
                    match text.trim().parse::<f64>() {
                        Ok(x) if x.is_finite() && p.steps_per_unit.is_some() => scaled(x),
                        _ => text,
                    }
                }
            };
            to.insert(k.clone(), value);
        }
        let needed = placeholders(&p.command).map_err(|m| m.at(key("move")))?;
        if let Some(extra) = to.keys().find(|k| !needed.contains(k)) {
            return Err(ValidationError::new(
                key(&format!("to.{extra}")),
                format!("{positioner}'s command {:?} has no {{{extra}}}", p.command),
            ));
        }
        let command = fill(&p.command, &mut |n| to.get(n).cloned()).map_err(|m| {
            ValidationError::new(key("to"), format!("{positioner}'s command needs it: {m}"))
        })?;
        let expect = s.expect.clone().unwrap_or_else(|| p.reply.clone());
        check_text(&expect).map_err(|m| m.at(key("expect")))?;
        Regex::new(&expect)
            .map_err(|e| ValidationError::new(key("expect"), pattern_message(&e)))?;
        let timeout_s = s.timeout_s.unwrap_or(p.timeout_s);
        if !(timeout_s > 0.0 && timeout_s <= limits::MAX_DURATION_MS / 1e3) {
            return Err(ValidationError::new(
                key("timeout_s"),
                duration_message(timeout_s),
            ));
        }
        let planned = self.move_time(p, &to);
        let action = Action::Move {
            positioner,
            command,
            expect,
            timeout_s,
            to,
        };
        self.push(name.to_string(), action, planned);
        Ok(())
    }

    /// A move's planned duration: a simulated stage's travel at its speed (its `angle` and
    /// `tilt` values), else the positioner's `move_s`.
    fn move_time(&mut self, p: &PositionerSpec, to: &BTreeMap<String, String>) -> f64 {
        let Some(stage) = &p.sim else {
            return p.move_s;
        };
        let here = self.axes.get(&p.name).copied().unwrap_or((0.0, 0.0));
        let get = |k: &str, d: f64| to.get(k).and_then(|v| v.parse().ok()).unwrap_or(d);
        let there = (get("angle", here.0), get("tilt", here.1));
        self.axes.insert(p.name.clone(), there);
        (there.0 - here.0).abs().max((there.1 - here.1).abs()) / stage.speed_deg_s
    }

    fn repeat(
        &mut self,
        s: &StepSpec,
        at: &str,
        vars: &Vars,
        round: &str,
        depth: usize,
    ) -> Result<(), ValidationError> {
        let key = |k: &str| format!("{at}.{k}");
        let n = s.repeat.unwrap_or(0);
        if n == 0 {
            return Err(ValidationError::new(key("repeat"), "repeat at least once"));
        }
        let steps = s.steps.as_deref().unwrap_or(&[]);
        if steps.is_empty() {
            return Err(ValidationError::new(key("steps"), "a repeat needs steps"));
        }
        let defined = s.vars.clone().unwrap_or_default();
        for (name, v) in &defined {
            check_var(name, v).map_err(|m| m.at(key(&format!("vars.{name}"))))?;
        }
        for i in 0..n {
            let mut inner = vars.clone();
            for (name, v) in &defined {
                inner.insert(name.clone(), var_value(v, i));
            }
            let round = format!("{round} (round {} of {n})", i + 1);
            self.block(steps, &key("steps"), &inner, &round, depth + 1)?;
            if self.out.len() > MAX_SCRIPT_STEPS {
                return Err(ValidationError::new(
                    key("repeat"),
                    format!("the script unrolls to more than {MAX_SCRIPT_STEPS} steps"),
                ));
            }
        }
        Ok(())
    }

    fn every(
        &mut self,
        s: &StepSpec,
        at: &str,
        name: &str,
        vars: &Vars,
    ) -> Result<(), ValidationError> {
        let key = |k: &str| format!("{at}.{k}");
        let period_s = s.every.unwrap_or(0.0);
        if !(period_s > 0.0 && period_s <= limits::MAX_DURATION_MS / 1e3) {
            return Err(ValidationError::new(
                key("every"),
                duration_message(period_s),
            ));
        }
        let count = s
            .count
            .ok_or_else(|| ValidationError::new(key("count"), "every needs a count"))?;
        if count == 0 || count as usize > limits::MAX_POSES {
            return Err(ValidationError::new(
                key("count"),
                format!("{count} captures: 1 to {}", limits::MAX_POSES),
            ));
        }
        let countdown_s = s.countdown_s.unwrap_or(3.0_f64.min(period_s));
        limits::non_negative(countdown_s, period_s).map_err(|m| m.at(key("countdown_s")))?;
        let label = s.label.clone().unwrap_or_else(|| "hand-held {i}".into());
        check_text(&label).map_err(|m| m.at(key("label")))?;
        let exposure = self.exposure(s, at)?;
        let group = self.groups;
        self.groups += 1;
        for index in 0..count {
            let label = fill(&label, &mut |n| match n {
                "i" => Some(index.to_string()),
                _ => vars.get(n).map(|&v| format_number(v)),
            })
            .map_err(|m| m.at(key("label")))?;
            let tick = Tick {
                group,
                index,
                period_s,
                countdown_s,
            };
            let step = format!("{name} #{index}");
            self.capture(step, label, Some(tick), exposure.clone());
        }
        Ok(())
    }
}

/// Which kind of step `s` is: exactly one kind key.
fn step_kind(s: &StepSpec) -> Result<&'static str, Invalid> {
    let kinds: Vec<&'static str> = [
        ("capture", s.capture.is_some()),
        ("wait", s.wait.is_some()),
        ("prompt", s.prompt.is_some()),
        ("move", s.move_to.is_some()),
        ("repeat", s.repeat.is_some()),
        ("every", s.every.is_some()),
    ]
    .into_iter()
    .filter_map(|(k, set)| set.then_some(k))
    .collect();
    match kinds.as_slice() {
        [one] => Ok(one),
        [] => Err("a step needs one of capture, wait, prompt, move, repeat, every".into()),
        many => Err(Invalid(format!(
            "one step, one kind: {} given",
            many.join(", ")
        ))),
    }
}

/// Keys that belong to another kind of step: the first, refused (at the key alone).
fn check_keys(s: &StepSpec, kind: &str) -> Result<(), ValidationError> {
    let owners: [(&'static str, bool, &[&str]); 11] = [
        ("to", s.to.is_some(), &["move"]),
        ("expect", s.expect.is_some(), &["move"]),
        ("timeout_s", s.timeout_s.is_some(), &["move", "prompt"]),
        ("vars", s.vars.is_some(), &["repeat"]),
        ("steps", s.steps.is_some(), &["repeat"]),
        ("count", s.count.is_some(), &["every"]),
        ("countdown_s", s.countdown_s.is_some(), &["every"]),
        ("label", s.label.is_some(), &["every"]),
        (
            "exposure_us",
            s.exposure_us.is_some(),
            &["capture", "every"],
        ),
        ("gain_db", s.gain_db.is_some(), &["capture", "every"]),
        ("cameras", s.cameras.is_some(), &["capture", "every"]),
    ];
    for (key, set, kinds) in owners {
        if set && !kinds.contains(&kind) {
            return Err(ValidationError::new(
                key,
                format!(
                    "a {kind} step takes no {key} (it is for {})",
                    kinds.join(", ")
                ),
            ));
        }
    }
    Ok(())
}

fn check_var(name: &str, v: &VarSpec) -> Result<(), Invalid> {
    let valid = name
        .chars()
        .next()
        .is_some_and(|c| c.is_alphabetic() || c == '_')
        && name.chars().all(|c| c.is_alphanumeric() || c == '_');
    if !valid || name == "i" {
        return Err(Invalid(format!("{name:?} cannot name a variable")));
    }
    match (&v.values, v.from, v.step) {
        (Some(values), None, None) if !values.is_empty() => limits::finite(values),
        (None, Some(from), step) => limits::finite(&[from, step.unwrap_or(0.0)]),
        _ => Err("give from (and step), or values".into()),
    }
}

fn var_value(v: &VarSpec, round: u32) -> f64 {
    match &v.values {
        Some(values) => values[round as usize % values.len()],
        None => v.from.unwrap_or(0.0) + f64::from(round) * v.step.unwrap_or(0.0),
    }
}

#[cfg(test)]
mod tests;
