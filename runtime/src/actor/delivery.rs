//! Sending an actor's batches so that the store gets every transition, through a store's restart.
//!
//! A send that iceoryx2 reports delivered to no store (not yet connected, or the store died) is
//! sent again under the same numbers. What the store has not acknowledged as appended
//! ([`StoreAck`]) stays in the [`Outbox`]. When a new store replaces the one the batches went to,
//! the sender sends all of it again, oldest first and before anything new, so the new store sees
//! each actor's numbers in order and drops what the dead one had already written as duplicates.
//! A replay sample needs no copies: the actor writes it again from the sample, from the first
//! unacknowledged number ([`Sent::Rewind`]).

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use uavmeta_proto::dataset::Transition;
use uavmeta_proto::payload::{StoreAck, TransitionSlot};

use super::metrics::ActorMetrics;
use super::{ActorError, Control, POLL};
use crate::liveness;
use crate::transport::{self, LoanedBatch, SubscriberSet, TransitionPublisher};

/// How long an actor whose outbox is full waits between looks for the store's acknowledgements.
/// About the store's own idle wait: an acknowledgement takes a few hundred microseconds to come
/// back on one host and milliseconds across a tunnel, and each look that finds one frees room for
/// a batch; waiting [`POLL`] (10 ms) instead left an actor behind a tunnel idle most of the time
/// (docs/BENCHMARKS.md, Remote actors).
const ACK_WAIT: Duration = Duration::from_micros(200);

/// What became of a batch handed to the [`Sender`].
pub(super) enum Sent {
    /// The store's queue has it, and everything kept before it.
    Delivered,
    /// A new store replaced the one the replay sample went to: send the sample again from this
    /// number, the first one the store has not acknowledged.
    Rewind(u64),
    /// A stop was requested while waiting for a store.
    Stopped,
}

/// Sends batches to the task's store and keeps what the store has not acknowledged.
pub(super) struct Sender<'a, 's> {
    port: Port<'a, 's>,
    acks: Subscriber<ipc::Service, StoreAck, ()>,
    task: u32,
    actor: u32,
    outbox: Outbox,
    /// Whether an acknowledgement has been read: the first says where the store stands.
    first_ack_seen: bool,
}

impl<'a, 's> Sender<'a, 's> {
    pub fn new(
        publisher: &'a TransitionPublisher<'s>,
        acks: Subscriber<ipc::Service, StoreAck, ()>,
        (task, actor): (u32, u32),
        metrics: &'a ActorMetrics,
    ) -> Self {
        Self {
            port: Port {
                link: StoreLink::default(),
                publisher,
                metrics,
                waited: Duration::ZERO,
                delivered_up_to: 0,
                published: 0,
            },
            acks,
            task,
            actor,
            outbox: Outbox::default(),
            first_ack_seen: false,
        }
    }

    /// Transitions delivered to a store, each counted once however often it was sent.
    pub fn published(&self) -> u64 {
        self.port.published
    }

    /// Time spent waiting for a store (none subscribed, or its queue full) since the last call.
    pub fn take_waited(&mut self) -> Duration {
        std::mem::take(&mut self.port.waited)
    }

    /// Reads the store's acknowledgements and forgets the batches they cover.
    pub fn read_acks(&mut self) -> Result<(), ActorError> {
        if let Some(next) = transport::latest_ack(&self.acks, self.task, self.actor)? {
            self.check_ack(next)?;
            self.outbox.acknowledged(next);
            self.show_kept();
        }
        Ok(())
    }

    /// After the first acknowledgement (where the store stands: what a predecessor of this actor,
    /// restarted, sent is in it), only this actor's own batches move the store's number on: one
    /// that moves beyond what this actor has sent means that another publisher sends under its
    /// id, which would have the store drop this actor's transitions as duplicates (issue #61).
    fn check_ack(&mut self, next: u64) -> Result<(), ActorError> {
        let sent = self.port.delivered_up_to;
        if !self.first_ack_seen {
            self.first_ack_seen = true;
            return Ok(());
        }
        match next > self.outbox.stored && next > sent {
            true => Err(ActorError::AckedBeyondSent {
                task: self.task,
                actor: self.actor,
                acknowledged: next,
                sent,
            }),
            false => Ok(()),
        }
    }

    fn show_kept(&self) {
        let kept = self.outbox.transitions();
        self.port.metrics.unacknowledged.set(kept as i64);
    }

    /// Sends a rollout's batch, written in place, keeping a copy until the store has it for good.
    pub fn send_rollout(
        &mut self,
        mut batch: LoanedBatch<'a, 's>,
        control: &Control,
    ) -> Result<Sent, ActorError> {
        if !self.wait_for_room(control)? {
            return Ok(Sent::Stopped);
        }
        let obs_len = self.port.publisher.obs_len();
        self.outbox.keep(batch.first_seq(), batch.slots(), obs_len);
        self.show_kept();
        let (first_seq, count) = (batch.first_seq(), batch.slots_mut().len());
        let outbox = &self.outbox;
        let rewrite = |slots: &mut [TransitionSlot]| slots.copy_from_slice(outbox.newest());
        match self.port.deliver(batch, rewrite, control)? {
            Outcome::Delivered => {
                self.port.count_delivered(first_seq, count);
                Ok(Sent::Delivered)
            }
            Outcome::Stopped => Ok(Sent::Stopped),
            Outcome::Replaced => self.resend_outbox(control),
        }
    }

    /// Waits while the outbox is full; false if a stop was requested meanwhile. The store
    /// acknowledges every batch it takes, and repeats its acknowledgements, so the outbox holds
    /// the store's queue and a batch or two; a full one means no store is acknowledging (one
    /// stopped, or a subscriber that is not a store), and the actor must not hoard memory for it.
    fn wait_for_room(&mut self, control: &Control) -> Result<bool, ActorError> {
        let room = 2 * self.port.publisher.subscriber_buffer() + 2;
        if self.outbox.batches.len() < room {
            return Ok(true);
        }
        tracing::warn!(
            batches = self.outbox.batches.len(),
            "the store has not acknowledged what it received; waiting"
        );
        while self.outbox.batches.len() >= room {
            // The batches may have gone nowhere (a tunnel that died with them, and a new one in
            // its place): no acknowledgement will come. Stop waiting; the delivery of this batch
            // sees the new subscriber and sends everything kept again (not from here: the
            // caller holds this batch's loan, and the publisher lends one at a time).
            if self.port.link.replaced(self.port.publisher.subscribers()) {
                return Ok(true);
            }
            let pause = Instant::now();
            let stop = control.stop_requested(ACK_WAIT)?;
            self.port.waited += pause.elapsed();
            if stop {
                return Ok(false);
            }
            self.read_acks()?;
        }
        Ok(true)
    }

    /// Sends a batch of the replay sample `sample`, written in place.
    pub fn send_sample(
        &mut self,
        batch: LoanedBatch<'a, 's>,
        sample: &[Transition],
        control: &Control,
    ) -> Result<Sent, ActorError> {
        let (first_seq, count) = (batch.first_seq(), batch.slots().len());
        let rewrite = |slots: &mut [TransitionSlot]| write_sample(slots, sample, first_seq);
        match self.port.deliver(batch, rewrite, control)? {
            Outcome::Delivered => {
                self.port.count_delivered(first_seq, count);
                Ok(Sent::Delivered)
            }
            Outcome::Stopped => Ok(Sent::Stopped),
            Outcome::Replaced => Ok(self.rewind()),
        }
    }

    /// Waits until the store has acknowledged everything sent, sending it again to a store that
    /// replaces the current one meanwhile; false if a stop was requested first.
    pub fn wait_until_stored(&mut self, control: &Control) -> Result<bool, ActorError> {
        loop {
            self.read_acks()?;
            if self.outbox.batches.is_empty() {
                return Ok(true);
            }
            let now = self.port.publisher.subscribers();
            if self.port.link.replaced(now) {
                self.port.link.observe(now);
                if let Sent::Stopped = self.resend_outbox(control)? {
                    return Ok(false);
                }
                continue;
            }
            let pause = Instant::now();
            let stop = control.stop_requested(POLL)?;
            self.port.waited += pause.elapsed();
            if stop {
                return Ok(false);
            }
        }
    }

    /// For an actor with nothing left to send: if a new store replaced the one the replay sample
    /// went to, where to send it again from.
    pub fn rewind_if_store_changed(&mut self) -> Option<u64> {
        let now = self.port.publisher.subscribers();
        let replaced = self.port.link.replaced(now);
        self.port.link.observe(now);
        replaced.then(|| match self.rewind() {
            Sent::Rewind(to) => to,
            _ => unreachable!("rewind() only rewinds"),
        })
    }

    fn rewind(&mut self) -> Sent {
        self.port.metrics.store_changes.inc();
        let to = self.outbox.stored;
        tracing::warn!(
            from = to,
            "the store changed; sending the replay sample again"
        );
        Sent::Rewind(to)
    }

    /// Sends everything kept again, oldest first, to the store that replaced the one it went to;
    /// starts over if that store is replaced in turn.
    fn resend_outbox(&mut self, control: &Control) -> Result<Sent, ActorError> {
        'again: loop {
            self.port.metrics.store_changes.inc();
            tracing::warn!(
                from = self.outbox.stored,
                transitions = self.outbox.transitions(),
                "the store changed; sending what it had not acknowledged again"
            );
            for kept in &self.outbox.batches {
                let mut batch = self.port.publisher.loan(kept.first_seq, kept.slots.len())?;
                batch.slots_mut().copy_from_slice(&kept.slots);
                let rewrite = |slots: &mut [TransitionSlot]| slots.copy_from_slice(&kept.slots);
                match self.port.deliver(batch, rewrite, control)? {
                    Outcome::Delivered => {
                        self.port.count_delivered(kept.first_seq, kept.slots.len())
                    }
                    Outcome::Replaced => continue 'again,
                    Outcome::Stopped => return Ok(Sent::Stopped),
                }
            }
            return Ok(Sent::Delivered);
        }
    }
}

/// What one [`Port::deliver`] came to.
enum Outcome {
    Delivered,
    /// A new store replaced the one earlier batches went to; the batch was not sent.
    Replaced,
    Stopped,
}

/// The publisher and what the actor knows of the store behind it.
struct Port<'a, 's> {
    publisher: &'a TransitionPublisher<'s>,
    link: StoreLink,
    metrics: &'a ActorMetrics,
    waited: Duration,
    /// Every number below this was delivered at least once: a delivery below it is a resend.
    delivered_up_to: u64,
    published: u64,
}

impl<'a, 's> Port<'a, 's> {
    /// Sends `batch` once a store is subscribed. After a send that reached nobody it sends the
    /// batch again, rewritten by `rewrite` under the same numbers; it returns
    /// [`Outcome::Replaced`] instead of sending to a store that replaced the last one.
    fn deliver(
        &mut self,
        mut batch: LoanedBatch<'a, 's>,
        rewrite: impl Fn(&mut [TransitionSlot]),
        control: &Control,
    ) -> Result<Outcome, ActorError> {
        let (first_seq, count) = (batch.first_seq(), batch.slots().len());
        loop {
            // Sent while no store is subscribed, the batch would be lost: hold it until one is.
            let subscribers = loop {
                let subscribers = self.publisher.subscribers();
                if !subscribers.is_empty() {
                    break subscribers;
                }
                let pause = Instant::now();
                let stop = control.stop_requested(POLL)?;
                self.waited += pause.elapsed();
                if stop {
                    return Ok(Outcome::Stopped);
                }
            };
            let replaced = self.link.replaced(subscribers);
            self.link.observe(subscribers);
            if replaced {
                return Ok(Outcome::Replaced);
            }
            let delivery = match batch.send() {
                Ok(delivery) => delivery,
                Err(_) if liveness::termination_requested() => return Ok(Outcome::Stopped),
                Err(error) => return Err(error.into()),
            };
            self.waited += delivery.backpressure;
            if delivery.recipients > 0 {
                return Ok(Outcome::Delivered);
            }
            // Not yet connected, or the store died: send it again under the same numbers.
            self.metrics.batches_resent.inc();
            batch = self.publisher.loan(first_seq, count)?;
            rewrite(batch.slots_mut());
        }
    }

    /// Counts a delivered batch: new numbers as published, the rest as resent.
    fn count_delivered(&mut self, first_seq: u64, count: usize) {
        let end = first_seq + count as u64;
        let new = end.saturating_sub(first_seq.max(self.delivered_up_to));
        self.delivered_up_to = self.delivered_up_to.max(end);
        self.published += new;
        self.metrics.transitions_published.inc_by(new);
        self.metrics.transitions_resent.inc_by(count as u64 - new);
        self.metrics.batches_published.inc();
    }
}

/// Copies of sent rollout batches the store has not acknowledged, oldest first.
#[derive(Default)]
struct Outbox {
    batches: VecDeque<Kept>,
    /// Copies no longer needed, reused so that keeping a batch allocates nothing once running.
    spare: Vec<Vec<TransitionSlot>>,
    /// The store's latest acknowledgement: every number below it is in the dataset file.
    stored: u64,
    /// Transitions in `batches`.
    kept: usize,
}

struct Kept {
    first_seq: u64,
    slots: Vec<TransitionSlot>,
}

impl Outbox {
    /// Keeps a copy of a sent batch whose slots use `obs_len` observation entries. Only those are
    /// copied: at batch 1024 the outbox outgrows the caches, and whole slots cost twice as much.
    fn keep(&mut self, first_seq: u64, slots: &[TransitionSlot], obs_len: usize) {
        let mut copy = self.spare.pop().unwrap_or_default();
        copy.resize(slots.len(), TransitionSlot::default());
        for (copy, slot) in copy.iter_mut().zip(slots) {
            copy.copy_written(slot, obs_len);
        }
        self.kept += copy.len();
        self.batches.push_back(Kept {
            first_seq,
            slots: copy,
        });
    }

    /// The batch kept last.
    fn newest(&self) -> &[TransitionSlot] {
        &self
            .batches
            .back()
            .expect("a batch is kept before it is sent")
            .slots
    }

    fn acknowledged(&mut self, next_seq: u64) {
        // A successor store rebuilds its numbers from the file, which holds at least what the
        // dead store acknowledged, so acknowledgements never go back.
        self.stored = self.stored.max(next_seq);
        while let Some(oldest) = self.batches.front() {
            if oldest.first_seq + oldest.slots.len() as u64 > self.stored {
                break;
            }
            let oldest = self.batches.pop_front().expect("a front batch");
            self.kept -= oldest.slots.len();
            self.spare.push(oldest.slots);
        }
    }

    fn transitions(&self) -> usize {
        self.kept
    }
}

/// The stores the actor's batches went to. iceoryx2 0.10 connects a subscriber to a new publisher
/// only when the subscriber next looks for data; until then a batch sent into its full queue is
/// dropped (0 recipients), which is why every rollout batch is kept until acknowledged.
#[derive(Debug, Default)]
struct StoreLink {
    /// Subscribers attached when the last batch was sent.
    subscribers: SubscriberSet,
}

impl StoreLink {
    /// A new store (or a dead one cleaned up) changes the set. No store at all changes nothing:
    /// the last one is remembered, to tell a successor.
    fn observe(&mut self, subscribers: SubscriberSet) {
        if !subscribers.is_empty() && subscribers != self.subscribers {
            self.subscribers = subscribers;
        }
    }

    /// True when a store is subscribed but the set differs from the one the last batch was sent
    /// to: a store that held batches may have died and been replaced.
    fn replaced(&self, now: SubscriberSet) -> bool {
        !self.subscribers.is_empty() && !now.is_empty() && now != self.subscribers
    }
}

/// Writes the replay sample's transitions `first_seq..` into `slots`.
pub(super) fn write_sample(slots: &mut [TransitionSlot], sample: &[Transition], first_seq: u64) {
    let range = first_seq as usize..first_seq as usize + slots.len();
    for (slot, t) in slots.iter_mut().zip(&sample[range]) {
        slot.set_transition(t);
    }
}

#[cfg(test)]
mod tests {
    use uavmeta_proto::payload::OBS_CAPACITY;

    use super::*;

    fn batch(first_seq: u64, count: usize) -> Vec<TransitionSlot> {
        (first_seq..first_seq + count as u64)
            .map(|seq| TransitionSlot {
                episode: seq,
                obs: [seq as u16; OBS_CAPACITY],
                ..TransitionSlot::default()
            })
            .collect()
    }

    #[test]
    fn the_outbox_forgets_only_whole_acknowledged_batches_and_reuses_their_memory() {
        let mut outbox = Outbox::default();
        for first in [0, 4, 8] {
            outbox.keep(first, &batch(first, 4), 5);
        }
        assert_eq!(outbox.newest()[0].episode, 8);
        outbox.acknowledged(6);
        assert_eq!(outbox.transitions(), 8, "4..8 is only half stored: kept");
        assert_eq!(outbox.batches.front().map(|b| b.first_seq), Some(4));
        outbox.acknowledged(2);
        assert_eq!(outbox.stored, 6, "an older acknowledgement changes nothing");
        outbox.acknowledged(12);
        assert_eq!(outbox.transitions(), 0);
        assert_eq!(outbox.spare.len(), 3);
        outbox.keep(12, &batch(12, 4), 5);
        assert_eq!(outbox.spare.len(), 2, "a spare copy is reused");
        let newest = &outbox.newest()[3];
        assert_eq!(newest.episode, 15);
        assert_eq!(newest.obs[..5], [15; 5], "the used entries are copied");
    }
}
