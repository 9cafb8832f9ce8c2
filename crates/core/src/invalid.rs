//! Refusals of what is read: one vocabulary for every check of a file or a value.
//!
//! [`Invalid`] says what is wrong with one value ("20000 poses: at most 10000"); where the
//! value sits makes it a [`ValidationError`]: the file (when known), the line (when known),
//! and the place within the file (a JSON path such as `views[3].camera` or a dotted TOML key
//! such as `camera[0].exposure_ms`). Its text is the one-line refusal hexcal prints,
//! `FILE:LINE: PATH: what is wrong`, each part present when known.

use std::fmt;
use std::path::PathBuf;

/// What is wrong with one value, as one line (e.g. "20000 poses: at most 10000"); where the
/// value is, is the caller's to say ([`Invalid::at`]).
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct Invalid(pub String);

impl Invalid {
    /// A refusal saying `message`.
    pub fn new(message: impl Into<String>) -> Invalid {
        Invalid(message.into())
    }

    /// What is wrong.
    pub fn message(&self) -> &str {
        &self.0
    }

    /// The refusal of the value at `at` (a JSON path or a dotted key).
    pub fn at(self, at: impl Into<String>) -> ValidationError {
        ValidationError::new(at, self.0)
    }
}

impl From<String> for Invalid {
    fn from(message: String) -> Invalid {
        Invalid(message)
    }
}

impl From<&str> for Invalid {
    fn from(message: &str) -> Invalid {
        Invalid(message.to_owned())
    }
}

impl From<Invalid> for String {
    fn from(invalid: Invalid) -> String {
        invalid.0
    }
}

/// The message, read as text (`contains`, `starts_with`, …).
impl std::ops::Deref for Invalid {
    type Target = str;

    fn deref(&self) -> &str {
        &self.0
    }
}

impl AsRef<str> for Invalid {
    fn as_ref(&self) -> &str {
        &self.0
    }
}

impl PartialEq<str> for Invalid {
    fn eq(&self, other: &str) -> bool {
        self.0 == other
    }
}

impl PartialEq<&str> for Invalid {
    fn eq(&self, other: &&str) -> bool {
        self.0 == *other
    }
}

/// A value of a file is wrong: where it is and what is wrong. Shown as
/// `FILE:LINE: AT: MESSAGE`, the file and line when known (`line N: AT: MESSAGE` for a
/// line without a file).
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub struct ValidationError {
    /// The file, when known.
    pub file: Option<PathBuf>,
    /// The line (1-based) of the value in the file, when known.
    pub line: Option<usize>,
    /// Where in the file: a JSON path (`views[3].camera`) or a dotted key
    /// (`camera[0].exposure_ms`).
    pub at: String,
    /// What is wrong.
    pub message: String,
}

impl ValidationError {
    /// The value at `at` is wrong: `message` (no file or line yet).
    pub fn new(at: impl Into<String>, message: impl Into<String>) -> ValidationError {
        ValidationError {
            file: None,
            line: None,
            at: at.into(),
            message: message.into(),
        }
    }

    /// The same refusal with `at` inside `prefix`: `prefix.at` (`views[3]` makes `camera`
    /// `views[3].camera`; an empty `at` becomes `prefix`).
    pub fn within(mut self, prefix: impl AsRef<str>) -> ValidationError {
        let prefix = prefix.as_ref();
        self.at = match (prefix.is_empty(), self.at.is_empty()) {
            (true, _) => self.at,
            (false, true) => prefix.to_owned(),
            (false, false) => format!("{prefix}.{}", self.at),
        };
        self
    }

    /// The same refusal with its place rewritten by `place` (given the place so far; e.g.
    /// a dotted key made a key of one camera table).
    pub fn map_at(mut self, place: impl FnOnce(&str) -> String) -> ValidationError {
        self.at = place(&self.at);
        self
    }

    /// The same refusal, of the value in `file`.
    pub fn in_file(mut self, file: impl Into<PathBuf>) -> ValidationError {
        self.file = Some(file.into());
        self
    }

    /// The same refusal, of the value on `line` (1-based) when known.
    pub fn on_line(mut self, line: Option<usize>) -> ValidationError {
        self.line = line;
        self
    }

    /// What is wrong, without where.
    pub fn invalid(&self) -> Invalid {
        Invalid(self.message.clone())
    }
}

impl fmt::Display for ValidationError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match (&self.file, self.line) {
            (Some(file), Some(line)) => write!(f, "{}:{line}: ", file.display())?,
            (Some(file), None) => write!(f, "{}: ", file.display())?,
            (None, Some(line)) => write!(f, "line {line}: ")?,
            (None, None) => {}
        }
        write!(f, "{}: {}", self.at, self.message)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_refusal_reads_file_line_path_message() {
        let e = Invalid::new("no camera").at("camera");
        assert_eq!(e.to_string(), "camera: no camera");
        let e = e.within("views[3]");
        assert_eq!(e.to_string(), "views[3].camera: no camera");
        let e = e.in_file("c.json");
        assert_eq!(e.to_string(), "c.json: views[3].camera: no camera");
        let e = e.on_line(Some(7));
        assert_eq!(e.to_string(), "c.json:7: views[3].camera: no camera");
        let e = ValidationError::new("", "x")
            .within("script[0]")
            .on_line(Some(2));
        assert_eq!(e.to_string(), "line 2: script[0]: x");
        assert_eq!(Invalid::from("a"), "a");
    }
}
