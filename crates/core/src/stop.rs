//! A request to stop (Ctrl-C, SIGTERM), as the long stages see it: the application layer
//! owns the flag its signal handler sets; a stage polls [`Stop::requested`] between steps
//! (an adjustment between iterations) and ends early, saying it stopped.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

/// A flag a stage polls to end early; [`Stop::default`] is never set.
#[derive(Clone, Debug, Default)]
pub struct Stop(Option<Arc<AtomicBool>>);

impl Stop {
    /// Stops once `flag` is set (by a signal handler, another thread).
    pub fn on(flag: Arc<AtomicBool>) -> Stop {
        Stop(Some(flag))
    }

    /// Whether a stop has been asked for.
    pub fn requested(&self) -> bool {
        self.0.as_ref().is_some_and(|f| f.load(Ordering::SeqCst))
    }
}

/// Two stops are equal when they watch the same flag (or neither watches one).
impl PartialEq for Stop {
    fn eq(&self, other: &Stop) -> bool {
        match (&self.0, &other.0) {
            (Some(a), Some(b)) => Arc::ptr_eq(a, b),
            (a, b) => a.is_none() && b.is_none(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_stop_sees_its_flag_and_only_its_own() {
        let flag = Arc::new(AtomicBool::new(false));
        let stop = Stop::on(Arc::clone(&flag));
        assert!(!stop.requested());
        assert!(!Stop::default().requested());
        flag.store(true, Ordering::SeqCst);
        assert!(stop.requested());
        assert_eq!(stop, stop.clone());
        assert_ne!(stop, Stop::on(Arc::new(AtomicBool::new(true))));
        assert_ne!(stop, Stop::default());
        assert_eq!(Stop::default(), Stop::default());
    }
}
