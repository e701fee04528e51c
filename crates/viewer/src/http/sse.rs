//! Server-sent events: an [`EventSource`] numbers the events a producer sends and keeps the last few, so a page
//! that reconnects (a reload, a dropped connection: the browser sends `Last-Event-ID`) gets what it missed; a
//! [`Subscription`] is one stream's position in it, answered with [`Response::events`](super::Response::events).
//!
//! While no event comes the server writes a comment (`: heartbeat`) every heartbeat interval (10 s unless
//! configured, below the 15 s idle limit and well below the 30 s write limit), so proxies and the browser keep a
//! silent stream open, and a client that is gone is noticed: its socket reads as closed, or a write to it fails
//! (at the latest when the write limit passes), and its thread and connection slot are freed.

use std::collections::VecDeque;
use std::io::Write;
use std::net::TcpStream;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

/// One event: its number (from 1, increasing by one), its type (`event:`; empty: the default `message`) and its
/// data (any text; several lines are sent as several `data:` lines, which the browser joins back).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Event {
    pub id: u64,
    pub event: String,
    pub data: String,
}

impl Event {
    /// The event in the wire format, ending with the blank line.
    pub fn encode(&self) -> String {
        let mut s = format!("id: {}\n", self.id);
        let name: String = self.event.chars().filter(|c| *c != '\n' && *c != '\r').collect();
        if !name.is_empty() {
            s.push_str(&format!("event: {name}\n"));
        }
        for line in self.data.split('\n') {
            s.push_str(&format!("data: {}\n", line.trim_end_matches('\r')));
        }
        s.push('\n');
        s
    }
}

struct State {
    /// The id the next event gets.
    next: u64,
    history: VecDeque<Event>,
    keep: usize,
    closed: bool,
}

struct Inner {
    state: Mutex<State>,
    changed: Condvar,
    streams: AtomicUsize,
}

/// Numbered events for any number of streams, the last `keep` of them kept for streams that resume. Cloning
/// gives another handle to the same source.
#[derive(Clone)]
pub struct EventSource(Arc<Inner>);

impl EventSource {
    /// A source that keeps the last `keep` events (at least 1) for streams that resume.
    pub fn new(keep: usize) -> Self {
        let state = State { next: 1, history: VecDeque::new(), keep: keep.max(1), closed: false };
        Self(Arc::new(Inner { state: Mutex::new(state), changed: Condvar::new(), streams: AtomicUsize::new(0) }))
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, State> {
        self.0.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Send an event of type `event` (empty: `message`) to every stream; its id.
    pub fn send(&self, event: &str, data: &str) -> u64 {
        let mut st = self.lock();
        let id = st.next;
        st.next += 1;
        st.history.push_back(Event { id, event: event.to_string(), data: data.to_string() });
        while st.history.len() > st.keep {
            st.history.pop_front();
        }
        drop(st);
        self.0.changed.notify_all();
        id
    }

    /// End every stream once it has sent what it holds (the browser reconnects after its retry delay; a stream
    /// opened later ends at once after the history). Sending stays possible.
    pub fn close(&self) {
        self.lock().closed = true;
        self.0.changed.notify_all();
    }

    /// The id of the last event sent (0: none yet).
    pub fn last_id(&self) -> u64 {
        self.lock().next - 1
    }

    /// The events still held, oldest first.
    pub fn history(&self) -> Vec<Event> {
        self.lock().history.iter().cloned().collect()
    }

    /// Streams open now (a route may refuse a second stream for a page, or close the source's older ones).
    pub fn streams(&self) -> usize {
        self.0.streams.load(Ordering::Acquire)
    }

    /// A stream's position: after `last_event_id` (the request's `Last-Event-ID`, see
    /// [`Request::last_event_id`](super::Request::last_event_id)), or from the oldest event held when None — or
    /// when the id is ahead of this source's (a source of an earlier run of the server).
    pub fn subscribe(&self, last_event_id: Option<u64>) -> Subscription {
        let last = self.last_id();
        let after = match last_event_id {
            Some(id) if id <= last => id,
            _ => 0,
        };
        self.0.streams.fetch_add(1, Ordering::AcqRel);
        Subscription { src: self.clone(), after }
    }
}

/// What [`Subscription::next`] found.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Next {
    /// Events after the stream's position (it moves past them). When events were dropped from the history
    /// before this stream saw them, the first is a `lost` event (id 0, not sent with an id; its data is the
    /// number lost): the page then fetches the whole state again.
    Events(Vec<Event>),
    /// None within the time given.
    Timeout,
    /// The source is closed and the stream has had everything.
    Closed,
}

/// One stream's position in an [`EventSource`].
pub struct Subscription {
    src: EventSource,
    after: u64,
}

impl Drop for Subscription {
    fn drop(&mut self) {
        self.src.0.streams.fetch_sub(1, Ordering::AcqRel);
    }
}

impl Subscription {
    /// The id of the last event this stream has had.
    pub fn position(&self) -> u64 {
        self.after
    }

    /// Wait at most `timeout` for events after this stream's position.
    pub fn next(&mut self, timeout: Duration) -> Next {
        let deadline = Instant::now() + timeout;
        let mut st = self.src.lock();
        loop {
            if st.next - 1 > self.after {
                let mut out = Vec::new();
                let oldest = st.history.front().map_or(st.next, |e| e.id);
                if oldest > self.after + 1 {
                    out.push(Event { id: 0, event: "lost".into(), data: (oldest - self.after - 1).to_string() });
                }
                out.extend(st.history.iter().filter(|e| e.id > self.after).cloned());
                self.after = st.next - 1;
                return Next::Events(out);
            }
            if st.closed {
                return Next::Closed;
            }
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Next::Timeout;
            }
            st = self.src.0.changed.wait_timeout(st, left).map(|(g, _)| g).unwrap_or_else(|p| p.into_inner().0);
        }
    }
}

/// Whether the peer has closed its side (or the socket failed): a read that would not block returns 0 or an
/// error. Bytes the client sent are left unread.
fn peer_gone(s: &TcpStream) -> bool {
    if s.set_nonblocking(true).is_err() {
        return true;
    }
    let mut b = [0u8; 1];
    let gone = match s.peek(&mut b) {
        Ok(0) => true,
        Ok(_) => false,
        Err(e) => !matches!(e.kind(), std::io::ErrorKind::WouldBlock | std::io::ErrorKind::Interrupted),
    };
    s.set_nonblocking(false).is_err() || gone
}

/// Write `sub`'s events to `s` until the source closes or the client goes; a heartbeat comment after each
/// `heartbeat` without an event. The head has been sent.
pub(crate) fn pump(s: &mut TcpStream, mut sub: Subscription, heartbeat: Duration) {
    // Reconnect after 2 s when the stream drops; the comment gets the headers through any buffering at once.
    if s.write_all(b"retry: 2000\n: stream open\n\n").and_then(|_| s.flush()).is_err() {
        return;
    }
    loop {
        if peer_gone(s) {
            return;
        }
        let chunk = match sub.next(heartbeat) {
            Next::Events(evs) => {
                evs.iter().map(|e| if e.id == 0 { format!("event: {}\ndata: {}\n\n", e.event, e.data) } else { e.encode() }).collect::<String>()
            }
            Next::Timeout => ": heartbeat\n\n".to_string(),
            Next::Closed => return,
        };
        // The write limit (the socket's write timeout) bounds each write to a client that stopped reading.
        if s.write_all(chunk.as_bytes()).and_then(|_| s.flush()).is_err() {
            return;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn resume_and_loss() {
        let src = EventSource::new(3);
        let mut a = src.subscribe(None);
        assert_eq!(a.next(Duration::from_millis(10)), Next::Timeout);
        for i in 1..=5 {
            assert_eq!(src.send("progress", &format!("{i}")), i);
        }
        // 1 and 2 were dropped from the history before `a` looked.
        let Next::Events(got) = a.next(Duration::ZERO) else { panic!() };
        assert_eq!(got.iter().map(|e| (e.id, e.event.as_str())).collect::<Vec<_>>(), vec![(0, "lost"), (3, "progress"), (4, "progress"), (5, "progress")]);
        assert_eq!(got[0].data, "2");
        let mut b = src.subscribe(Some(4));
        let Next::Events(got) = b.next(Duration::ZERO) else { panic!() };
        assert_eq!(got.iter().map(|e| e.id).collect::<Vec<_>>(), vec![5]);
        // An id from another run (ahead of this source): from the start.
        let c = src.subscribe(Some(99));
        assert_eq!(c.position(), 0);
        assert_eq!(src.streams(), 3);
        drop(c);
        assert_eq!(src.streams(), 2);
        src.close();
        assert_eq!(b.next(Duration::from_secs(5)), Next::Closed);
        assert_eq!(Event { id: 7, event: "log".into(), data: "a\nb".into() }.encode(), "id: 7\nevent: log\ndata: a\ndata: b\n\n");
    }
}
