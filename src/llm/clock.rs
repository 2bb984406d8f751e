//! The reply's clock: the limits a reply is read under besides the transport's silence limit.
//!
//! The silence limit (`--llm-timeout`) bounds each wait for bytes, and a server can keep
//! every such wait short while never finishing: SSE keep-alive comments or empty chunks
//! forever, one token a second forever, a JSON body one byte a second. Two more limits bound
//! those: a stream that brings no token (content or reasoning) for the silence limit has
//! stalled, whatever bytes it sends; and a reply, retries and waits between them included,
//! that is not complete by the deadline (`--reply-deadline`) is abandoned.
//!
//! Both are checked before each read of the body, so they hold as long as bytes keep coming;
//! a server that falls silent is given up on by the silence limit, which is then cut to the
//! time left before the deadline ([`ReplyClock::remaining`]).

use std::cell::Cell;
use std::io::Read;
use std::rc::Rc;
use std::time::{Duration, Instant};

use super::LlmError;

/// Why the clock stopped a read.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum Abandoned {
    /// The reply's deadline passed.
    #[error("the reply deadline passed")]
    Deadline,
    /// No token came for the progress limit.
    #[error("no token came for the progress limit")]
    NoProgress,
}

/// The limits of one reply, shared by the reads of its body (cheap to clone: clones share
/// the time of the last token).
#[derive(Debug, Clone)]
pub struct ReplyClock {
    start: Instant,
    deadline: Duration,
    progress: Duration,
    last_token: Rc<Cell<Instant>>,
}

impl ReplyClock {
    /// A clock for a reply first asked for at `start`: complete within `deadline` of it, and
    /// a streamed reply never `progress` without a token.
    pub fn new(start: Instant, deadline: Duration, progress: Duration) -> Self {
        Self {
            start,
            deadline,
            progress,
            last_token: Rc::new(Cell::new(Instant::now())),
        }
    }

    /// Time since the reply was first asked for.
    pub fn elapsed(&self) -> Duration {
        self.start.elapsed()
    }

    /// The deadline, from the first request.
    pub fn deadline(&self) -> Duration {
        self.deadline
    }

    /// The progress limit.
    pub fn progress(&self) -> Duration {
        self.progress
    }

    /// Time left before the deadline (zero once it passed).
    pub fn remaining(&self) -> Duration {
        self.deadline.saturating_sub(self.elapsed())
    }

    /// Whether the deadline passed.
    pub fn expired(&self) -> bool {
        self.remaining().is_zero()
    }

    /// The progress limit starts now (a stream's head arrived).
    pub fn restart_progress(&self) {
        self.last_token.set(Instant::now());
    }

    /// A token (content or reasoning) arrived.
    pub fn token(&self) {
        self.last_token.set(Instant::now());
    }

    /// Whether a read may go on: not past the deadline, and (`watch_progress`) not longer than
    /// the progress limit since the last token.
    pub fn check(&self, watch_progress: bool) -> Result<(), Abandoned> {
        if self.expired() {
            return Err(Abandoned::Deadline);
        }
        if watch_progress && self.last_token.get().elapsed() >= self.progress {
            return Err(Abandoned::NoProgress);
        }
        Ok(())
    }

    /// The error for a reply to `url` abandoned at the deadline, having `received` (in words:
    /// `12 tokens`, `300 bytes of a JSON body`).
    pub fn past_deadline(&self, url: &str, received: &str) -> LlmError {
        LlmError::Deadline {
            url: url.into(),
            elapsed: self.elapsed().as_secs_f64(),
            deadline: self.deadline.as_secs_f64(),
            received: received.into(),
        }
    }

    /// `inner` read under this clock: each read first [`check`](Self::check)s it.
    pub fn reader<R: Read>(&self, inner: R, watch_progress: bool) -> Timed<R> {
        Timed {
            inner,
            clock: self.clone(),
            watch_progress,
        }
    }
}

/// The clock's verdict in a failed read, if it was the clock that failed it.
pub fn abandoned(e: &std::io::Error) -> Option<Abandoned> {
    e.get_ref()
        .and_then(|r| r.downcast_ref::<Abandoned>())
        .copied()
}

/// A body read under a [`ReplyClock`]: a read past a limit fails with an [`std::io::Error`]
/// carrying [`Abandoned`] ([`abandoned`] finds it).
pub struct Timed<R> {
    inner: R,
    clock: ReplyClock,
    watch_progress: bool,
}

impl<R: Read> Read for Timed<R> {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        self.clock
            .check(self.watch_progress)
            .map_err(std::io::Error::other)?;
        self.inner.read(buf)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// One byte per read, `gap` apart: a server that trickles.
    struct Trickle(Duration);

    impl Read for Trickle {
        fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
            std::thread::sleep(self.0);
            buf[0] = b':';
            Ok(1)
        }
    }

    #[test]
    fn an_endless_trickle_ends_at_the_deadline_or_at_the_progress_limit() {
        let gap = Duration::from_millis(10);
        let clock = ReplyClock::new(
            Instant::now(),
            Duration::from_millis(200),
            Duration::from_secs(60),
        );
        let mut buf = Vec::new();
        let t0 = Instant::now();
        let e = clock
            .reader(Trickle(gap), true)
            .read_to_end(&mut buf)
            .unwrap_err();
        assert_eq!(abandoned(&e), Some(Abandoned::Deadline));
        assert!(t0.elapsed() < Duration::from_secs(2), "{:?}", t0.elapsed());
        assert!(buf.len() > 5, "{}", buf.len());
        // Bytes without tokens: the progress limit ends it, long before the deadline.
        let clock = ReplyClock::new(
            Instant::now(),
            Duration::from_secs(60),
            Duration::from_millis(100),
        );
        let e = clock
            .reader(Trickle(gap), true)
            .read_to_end(&mut Vec::new())
            .unwrap_err();
        assert_eq!(abandoned(&e), Some(Abandoned::NoProgress));
        // ... unless tokens keep coming.
        let r = clock.clone();
        clock.restart_progress();
        let mut timed = clock.reader(Trickle(gap), true);
        let mut one = [0u8; 1];
        for _ in 0..30 {
            r.token();
            timed.read_exact(&mut one).unwrap();
        }
        // A JSON body has no tokens to watch: only the deadline holds it.
        let mut plain = clock.reader(Trickle(gap), false);
        for _ in 0..30 {
            plain.read_exact(&mut one).unwrap();
        }
        assert!(abandoned(&std::io::Error::other("x")).is_none());
    }
}
