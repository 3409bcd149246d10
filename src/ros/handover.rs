//! Lock-free hand-over between a real-time control loop and the threads around it.
//!
//! rosrust runs each subscriber callback and each service on threads of its own. When
//! those threads and a `SCHED_FIFO` control loop share a `Mutex`, the loop waits whenever
//! an ordinary thread holding the lock is preempted (priority inversion). The three tools
//! here let the loop read its inputs, answer requests and hand out results without taking
//! a lock the other side holds, and without allocating on its side:
//!
//! - [`latest`]: a latest-value slot (a triple buffer, the `triple_buffer` crate) for `Copy`
//!   inputs written by one subscriber thread, e.g. `Option<Stamped<JointVector>>`, or an
//!   input fault as a fixed-capacity [`FaultText`]. The reader always gets the newest
//!   complete value, never a torn one, wait-free.
//! - [`requests`]: a bounded request queue (`crossbeam_queue::ArrayQueue`) from service
//!   threads (`~start`, `~abort`, `~reset`) to the loop, with the reply sent back through a
//!   one-shot channel (the `oneshot` crate). The
//!   caller waits for the reply with a timeout and gets a clear error when the loop does
//!   not answer; a request that timed out before the loop took it is never carried out.
//! - [`outputs`]: a bounded output queue from the loop to a publisher thread, which is
//!   woken with `std::thread::park`/`unpark`. The loop pushes a fixed-size `Copy` summary
//!   of its step; the publisher thread builds and sends the messages (rosrust's `send`
//!   allocates). When the publisher falls behind, the oldest summary is dropped and
//!   counted, never the loop delayed.
//!
//! What allocates where: the writer, the service and the publisher threads may allocate
//! (a request's state and its one-shot reply channel are made by the caller). The loop's operations,
//! [`SlotReader::read`], [`SlotReader::read_new`], [`RequestServer::serve`] (apart from
//! whatever the handler itself does) and [`OutputSender::push`], allocate nothing and take
//! no lock. One rare exception is stated where it applies: when a caller gave up on a
//! request and dropped its end, the loop frees the request's state and channel.
//!
//! How a control node uses them (a sketch):
//!
//! ```text
//! set-up:   (joints_w, joints_r) = latest(None)            one slot per input, and one
//!           (fault_w, fault_r) = latest(None::<FaultText>)  fault slot per input
//!           (client, server) = requests::<Request, Result<String, String>>(8)
//!           (tx, rx) = outputs::<StepSummary>(64)          StepSummary: Copy, fixed size
//!           subscriber callback: joints_w.write(Some(stamped)) or fault_w.write(Some(text))
//!           service callback:    client.call(Request::Start, timeout) -> Trigger reply
//!           publisher thread:    loop { rx.recv_timeout(..) -> build and send messages }
//! loop:     read:  joints = joints_r.read(); a new fault = fault_r.read_new()
//!           serve: server.serve(|r| match r { Start => core.start(), .. })
//!           step:  out = core.step(..)
//!           write: tx.push(summary of out)
//! ```

use std::fmt;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicU8, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::thread::Thread;
use std::time::{Duration, Instant};

use crossbeam_queue::ArrayQueue;

// ---------------------------------------------------------------------------------------
// (a) The latest value of an input.

/// Create a latest-value slot holding `initial`: one writer (a subscriber thread), one
/// reader (the control loop).
pub fn latest<T: Copy + Send>(initial: T) -> (SlotWriter<T>, SlotReader<T>) {
    let (input, output) = triple_buffer::triple_buffer(&initial);
    (
        SlotWriter {
            input: Mutex::new(input),
        },
        SlotReader { output },
    )
}

/// The writing end of a [`latest`] slot. `Sync`, so a rosrust callback (an `Fn`) can own
/// it; its mutex is only ever taken by writers, never by the reader, so the reader cannot
/// wait on it.
pub struct SlotWriter<T: Send> {
    input: Mutex<triple_buffer::Input<T>>,
}

impl<T: Copy + Send> SlotWriter<T> {
    /// Publish `value`: the reader's next read returns it (or a newer one).
    pub fn write(&self, value: T) {
        self.input.lock().unwrap_or_else(|p| p.into_inner()).write(value);
    }
}

impl<T: Send> fmt::Debug for SlotWriter<T> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("SlotWriter")
    }
}

/// The reading end of a [`latest`] slot: wait-free, allocation-free.
pub struct SlotReader<T: Send> {
    output: triple_buffer::Output<T>,
}

impl<T: Copy + Send> SlotReader<T> {
    /// The newest value written (the initial value before any write).
    pub fn read(&mut self) -> T {
        *self.output.read()
    }

    /// The newest value if one was written since the last read, else `None`.
    pub fn read_new(&mut self) -> Option<T> {
        self.output.update().then(|| *self.output.output_buffer())
    }
}

impl<T: Send> fmt::Debug for SlotReader<T> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("SlotReader")
    }
}

/// Text of at most `N` bytes, stored inline (the UTF-8 bytes in a `tinyvec::ArrayVec`,
/// only ever whole characters), so that it is `Copy` and can travel through a [`latest`]
/// slot or an [`outputs`] queue without allocating. Longer text is cut at a character
/// boundary, with `…` at the end.
#[derive(Clone, Copy, PartialEq, Eq, Default)]
pub struct FixedText<const N: usize>(tinyvec::ArrayVec<[u8; N]>);

/// An input fault (why an input was rejected) as the loop receives it.
pub type FaultText = FixedText<240>;

impl<const N: usize> FixedText<N> {
    /// Empty text.
    pub const fn empty() -> Self {
        Self(tinyvec::ArrayVec::from_array_empty([0; N]))
    }

    /// `text`, cut to at most `N` bytes.
    pub fn new(text: &str) -> Self {
        let mut t = Self::empty();
        let _ = fmt::Write::write_str(&mut t, text);
        t
    }

    /// `value` formatted, cut to at most `N` bytes, without allocating.
    pub fn from_display(value: &impl fmt::Display) -> Self {
        let mut t = Self::empty();
        let _ = fmt::Write::write_fmt(&mut t, format_args!("{value}"));
        t
    }

    /// The text.
    pub fn as_str(&self) -> &str {
        // Only whole `&str`s cut at character boundaries are pushed: always UTF-8.
        std::str::from_utf8(&self.0).unwrap_or_default()
    }

    /// Whether the text is empty.
    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }
}

impl<const N: usize> fmt::Write for FixedText<N> {
    fn write_str(&mut self, s: &str) -> fmt::Result {
        const ELLIPSIS: &str = "…";
        let room = N - self.0.len();
        if s.len() <= room {
            self.0.extend_from_slice(s.as_bytes());
            return Ok(());
        }
        // Cut at a character boundary, leaving room for the ellipsis when there is any.
        let keep = room.saturating_sub(ELLIPSIS.len());
        let cut = (0..=keep).rev().find(|&i| s.is_char_boundary(i)).unwrap_or(0);
        self.0.extend_from_slice(&s.as_bytes()[..cut]);
        if room - cut >= ELLIPSIS.len() {
            self.0.extend_from_slice(ELLIPSIS.as_bytes());
        }
        Err(fmt::Error)
    }
}

impl<const N: usize> fmt::Debug for FixedText<N> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        fmt::Debug::fmt(self.as_str(), f)
    }
}

impl<const N: usize> fmt::Display for FixedText<N> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

// ---------------------------------------------------------------------------------------
// (b) Requests to the loop, with a reply.

/// Why a request got no reply.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum HandoverError {
    /// The queue is full: the loop has not taken the requests before this one.
    #[error("the control loop has {capacity} requests waiting and takes no more (is it running?)")]
    Full {
        /// The queue's capacity.
        capacity: usize,
    },
    /// The loop did not take the request in time; it was withdrawn and will not be run.
    #[error("the control loop did not take the request within {} ms (is it running?); the request was withdrawn", .after.as_millis())]
    Timeout {
        /// How long the caller waited.
        after: Duration,
    },
    /// The loop took the request but sent no reply in time: it may have been carried out.
    #[error("the control loop took the request but did not reply within {} ms; it may have been carried out", .after.as_millis())]
    NoReply {
        /// How long the caller waited.
        after: Duration,
    },
}

const WAITING: u8 = 0;
const TAKEN: u8 = 1;
const WITHDRAWN: u8 = 2;

/// One request in the queue: whether the loop took it or its caller withdrew it, and the
/// one-shot channel its reply goes back through.
struct Pending<Q, R> {
    request: Q,
    state: Arc<AtomicU8>,
    reply: oneshot::Sender<R>,
}

/// Create a request queue of `capacity` (at least 1) requests `Q` with replies `R`.
pub fn requests<Q: Send, R: Send>(capacity: usize) -> (RequestClient<Q, R>, RequestServer<Q, R>) {
    let queue = Arc::new(ArrayQueue::new(capacity.max(1)));
    (RequestClient { queue: queue.clone() }, RequestServer { queue })
}

/// The callers' end (service threads): cloneable.
pub struct RequestClient<Q, R> {
    queue: Arc<ArrayQueue<Pending<Q, R>>>,
}

impl<Q, R> Clone for RequestClient<Q, R> {
    fn clone(&self) -> Self {
        Self {
            queue: self.queue.clone(),
        }
    }
}

impl<Q, R> fmt::Debug for RequestClient<Q, R> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("RequestClient")
            .field("waiting", &self.queue.len())
            .finish()
    }
}

impl<Q: Send, R: Send> RequestClient<Q, R> {
    /// Send `request` to the loop and wait (parked) for its reply, at most `timeout` for
    /// the loop to take it and as long again for the reply once taken. A request the loop
    /// did not take in time is withdrawn: the loop will skip it.
    pub fn call(&self, request: Q, timeout: Duration) -> Result<R, HandoverError> {
        let state = Arc::new(AtomicU8::new(WAITING));
        let (reply, answer) = oneshot::channel();
        let pending = Pending {
            request,
            state: state.clone(),
            reply,
        };
        if self.queue.push(pending).is_err() {
            return Err(HandoverError::Full {
                capacity: self.queue.capacity(),
            });
        }
        let t0 = Instant::now();
        if let Ok(r) = answer.recv_timeout(timeout) {
            return Ok(r);
        }
        let withdrawn = state.compare_exchange(WAITING, WITHDRAWN, Ordering::AcqRel, Ordering::Acquire);
        match withdrawn {
            Ok(_) => Err(HandoverError::Timeout { after: t0.elapsed() }),
            // Taken: the loop is on it; wait for the reply as long again, once.
            Err(_) => answer
                .recv_timeout(timeout)
                .map_err(|_| HandoverError::NoReply { after: t0.elapsed() }),
        }
    }
}

/// The loop's end: [`RequestServer::serve`] once per step.
pub struct RequestServer<Q, R> {
    queue: Arc<ArrayQueue<Pending<Q, R>>>,
}

impl<Q, R> fmt::Debug for RequestServer<Q, R> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("RequestServer")
            .field("waiting", &self.queue.len())
            .finish()
    }
}

impl<Q: Send, R: Send> RequestServer<Q, R> {
    /// Run `handle` on every waiting request, in order, and send each reply to its caller;
    /// returns how many were handled. Withdrawn requests are dropped unhandled. Lock-free
    /// and allocation-free itself (a withdrawn request's state and channel are freed here when its
    /// caller already dropped it).
    pub fn serve(&self, mut handle: impl FnMut(Q) -> R) -> usize {
        let mut handled = 0;
        while let Some(Pending { request, state, reply }) = self.queue.pop() {
            let taken = state.compare_exchange(WAITING, TAKEN, Ordering::AcqRel, Ordering::Acquire);
            if taken.is_err() {
                continue; // withdrawn by a caller that timed out
            }
            // Sending wakes the waiting caller; a caller already gone drops the reply.
            let _ = reply.send(handle(request));
            handled += 1;
        }
        handled
    }
}

// ---------------------------------------------------------------------------------------
// (c) Outputs of the loop, to a publisher thread.

struct OutputShared<T> {
    queue: ArrayQueue<T>,
    consumer: OnceLock<Thread>,
    closed: AtomicBool,
    dropped: AtomicU64,
}

/// Create an output queue of `capacity` (at least 1) items, from the loop to one consumer
/// thread.
pub fn outputs<T: Send>(capacity: usize) -> (OutputSender<T>, OutputReceiver<T>) {
    let shared = Arc::new(OutputShared {
        queue: ArrayQueue::new(capacity.max(1)),
        consumer: OnceLock::new(),
        closed: AtomicBool::new(false),
        dropped: AtomicU64::new(0),
    });
    (OutputSender { shared: shared.clone() }, OutputReceiver { shared })
}

/// The loop's end of an [`outputs`] queue. Dropping it closes the queue.
pub struct OutputSender<T> {
    shared: Arc<OutputShared<T>>,
}

impl<T> fmt::Debug for OutputSender<T> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("OutputSender")
            .field("queued", &self.shared.queue.len())
            .finish()
    }
}

impl<T: Send> OutputSender<T> {
    /// Queue `item` and wake the consumer; when the queue is full the oldest item is
    /// dropped (and counted) to make room. Returns whether one was. Lock-free,
    /// allocation-free.
    pub fn push(&self, item: T) -> bool {
        let displaced = self.shared.queue.force_push(item).is_some();
        if displaced {
            self.shared.dropped.fetch_add(1, Ordering::Relaxed);
        }
        if let Some(t) = self.shared.consumer.get() {
            t.unpark();
        }
        displaced
    }

    /// Items dropped so far because the consumer fell behind.
    pub fn dropped(&self) -> u64 {
        self.shared.dropped.load(Ordering::Relaxed)
    }
}

impl<T> Drop for OutputSender<T> {
    fn drop(&mut self) {
        self.shared.closed.store(true, Ordering::Release);
        if let Some(t) = self.shared.consumer.get() {
            t.unpark();
        }
    }
}

/// Why [`OutputReceiver::recv_timeout`] returned no item.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum RecvError {
    /// Nothing arrived in time.
    #[error("no output within the timeout")]
    Timeout,
    /// The sender is gone and the queue is empty.
    #[error("the control loop closed its output queue")]
    Closed,
}

/// The consumer's end of an [`outputs`] queue: one thread (the first to wait on it is the
/// one the sender wakes).
pub struct OutputReceiver<T> {
    shared: Arc<OutputShared<T>>,
}

impl<T> fmt::Debug for OutputReceiver<T> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("OutputReceiver")
            .field("queued", &self.shared.queue.len())
            .finish()
    }
}

impl<T: Send> OutputReceiver<T> {
    /// The oldest queued item, waiting (parked) up to `timeout` for one.
    pub fn recv_timeout(&self, timeout: Duration) -> Result<T, RecvError> {
        let _ = self.shared.consumer.get_or_init(std::thread::current);
        let deadline = Instant::now() + timeout;
        loop {
            if let Some(item) = self.shared.queue.pop() {
                return Ok(item);
            }
            if self.shared.closed.load(Ordering::Acquire) {
                return self.shared.queue.pop().ok_or(RecvError::Closed);
            }
            let now = Instant::now();
            if now >= deadline {
                return Err(RecvError::Timeout);
            }
            std::thread::park_timeout(deadline - now);
        }
    }

    /// The oldest queued item, if any, without waiting.
    pub fn try_recv(&self) -> Option<T> {
        self.shared.queue.pop()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_alloc::allocations_on_this_thread;

    #[test]
    fn a_reader_sees_whole_values_in_order_while_a_writer_writes() {
        let (w, mut r) = latest((0u64, 0u64, 0u64));
        const N: u64 = 200_000;
        let writer = std::thread::spawn(move || {
            for k in 1..=N {
                w.write((k, 2 * k, 3 * k));
            }
        });
        let (mut last, mut reads) = (0, 0u64);
        let before = allocations_on_this_thread();
        while last < N {
            let (a, b, c) = r.read();
            assert!(b == 2 * a && c == 3 * a, "torn value ({a}, {b}, {c})");
            assert!(a >= last, "went back from {last} to {a}");
            last = a;
            reads += 1;
        }
        assert_eq!(allocations_on_this_thread(), before, "the reader allocated");
        writer.join().unwrap();
        assert!(reads > 0);
        assert_eq!(r.read_new(), None);
    }

    #[test]
    fn read_new_tells_a_fresh_value_from_an_old_one() {
        let (w, mut r) = latest(None::<f64>);
        assert_eq!(r.read(), None);
        assert_eq!(r.read_new(), None);
        w.write(Some(1.5));
        assert_eq!(r.read_new(), Some(Some(1.5)));
        assert_eq!(r.read_new(), None);
        assert_eq!(r.read(), Some(1.5));
    }

    #[test]
    fn fixed_text_is_cut_at_a_character_boundary() {
        let t = FixedText::<16>::new("joint 'lbr_joint_7' is NaN");
        assert!(t.as_str().ends_with('…') && t.as_str().len() <= 16, "{t}");
        assert!("joint 'lbr_joint_7' is NaN".starts_with(t.as_str().trim_end_matches('…')));
        let t = FixedText::<8>::new("ééééé"); // 2 bytes each
        assert_eq!(t.as_str(), "éé…");
        assert_eq!(FixedText::<8>::new("short").as_str(), "short");
        let before = allocations_on_this_thread();
        let f = FaultText::from_display(&format_args!("stamp went back by {:.3} s", 0.25));
        assert_eq!(allocations_on_this_thread(), before);
        assert_eq!(f.as_str(), "stamp went back by 0.250 s");
        assert!(FaultText::default().is_empty());
    }

    #[test]
    fn a_request_gets_its_reply_from_the_loop() {
        let (client, server) = requests::<u32, String>(4);
        let stop = Arc::new(AtomicBool::new(false));
        let looping = {
            let stop = stop.clone();
            std::thread::spawn(move || {
                let mut served = 0;
                while !stop.load(Ordering::Relaxed) {
                    served += server.serve(|q| format!("started {q}"));
                    std::thread::sleep(Duration::from_millis(1));
                }
                served
            })
        };
        let callers: Vec<_> = (0..3)
            .map(|k| {
                let c = client.clone();
                std::thread::spawn(move || c.call(k, Duration::from_secs(5)))
            })
            .collect();
        let mut replies: Vec<String> = callers.into_iter().map(|h| h.join().unwrap().unwrap()).collect();
        replies.sort();
        assert_eq!(replies, ["started 0", "started 1", "started 2"]);
        stop.store(true, Ordering::Relaxed);
        assert_eq!(looping.join().unwrap(), 3);
    }

    #[test]
    fn a_loop_that_does_not_answer_gives_a_clear_timeout_and_skips_the_request() {
        let (client, server) = requests::<&str, ()>(1);
        let t0 = Instant::now();
        let e = client.call("start", Duration::from_millis(50)).unwrap_err();
        assert!(matches!(e, HandoverError::Timeout { .. }), "{e}");
        assert!(t0.elapsed() >= Duration::from_millis(50) && t0.elapsed() < Duration::from_secs(2));
        assert!(e.to_string().contains("did not take the request within"), "{e}");
        // The withdrawn request still fills the one slot: the next caller is told at once.
        let e = client.call("abort", Duration::from_secs(5)).unwrap_err();
        assert_eq!(e, HandoverError::Full { capacity: 1 });
        // The loop comes back: the withdrawn request is skipped, not run.
        let mut ran = Vec::new();
        assert_eq!(server.serve(|q| ran.push(q)), 0);
        assert!(ran.is_empty());
        let before = allocations_on_this_thread();
        assert_eq!(server.serve(|q| ran.push(q)), 0);
        assert_eq!(allocations_on_this_thread(), before, "an idle serve allocated");
    }

    #[test]
    fn the_loop_replies_without_allocating() {
        let (client, server) = requests::<u32, u32>(2);
        let caller = std::thread::spawn(move || client.call(7, Duration::from_secs(5)));
        let before = allocations_on_this_thread();
        let mut served = 0;
        while served == 0 {
            served = server.serve(|q| 2 * q);
            std::thread::yield_now();
        }
        assert_eq!(allocations_on_this_thread(), before, "serving a request allocated");
        assert_eq!(caller.join().unwrap(), Ok(14));
    }

    #[test]
    fn a_request_taken_but_not_answered_in_time_is_no_reply() {
        let (client, server) = requests::<u8, u8>(1);
        let looping = std::thread::spawn(move || {
            while server.serve(|q| {
                std::thread::sleep(Duration::from_millis(1500));
                q
            }) == 0
            {
                std::thread::sleep(Duration::from_millis(1));
            }
        });
        let e = client.call(1, Duration::from_millis(300)).unwrap_err();
        assert!(matches!(e, HandoverError::NoReply { .. }), "{e}");
        assert!(e.to_string().contains("may have been carried out"), "{e}");
        looping.join().unwrap();
    }

    #[test]
    fn outputs_wake_the_consumer_in_order_and_drop_the_oldest_when_full() {
        let (tx, rx) = outputs::<u32>(4);
        let consumer = std::thread::spawn(move || {
            let mut got = Vec::new();
            loop {
                match rx.recv_timeout(Duration::from_secs(5)) {
                    Ok(v) => got.push(v),
                    Err(RecvError::Closed) => return Ok(got),
                    Err(e) => return Err(e),
                }
            }
        });
        let before = allocations_on_this_thread();
        for k in 0..100 {
            tx.push(k);
            std::thread::sleep(Duration::from_micros(200));
        }
        assert_eq!(allocations_on_this_thread(), before, "push allocated");
        drop(tx);
        let got = consumer.join().unwrap().unwrap();
        assert!(got.windows(2).all(|w| w[0] < w[1]), "out of order: {got:?}");
        assert_eq!(got.last(), Some(&99));

        let (tx, rx) = outputs::<u32>(2);
        assert!(!tx.push(1) && !tx.push(2));
        assert!(tx.push(3), "a full queue drops its oldest");
        assert_eq!(tx.dropped(), 1);
        assert_eq!(rx.try_recv(), Some(2));
        assert_eq!(rx.recv_timeout(Duration::from_millis(1)), Ok(3));
        assert_eq!(rx.recv_timeout(Duration::from_millis(5)), Err(RecvError::Timeout));
    }
}
