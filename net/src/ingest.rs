//! What the frame loop does with each message the network task delivers, shared by
//! `tetwave stream` and the viewer: keep the manifest, build the session on the base mesh (and
//! keep it when a resumed connection sends the same base again), set the level set's band
//! whether it comes before or after the base, insert node batches, and at the stream's end
//! re-request what is missing, a bounded number of times.

use crate::connection::{check_hierarchy, Delivery};
use crate::error::{HttpError, NetError};
use crate::MAX_WANT_ROUNDS;
use tetwave_adaptive::session::Session;
use tetwave_protocol::levelset::NearLevelSet;
use tetwave_protocol::store_format::Manifest;
use tetwave_protocol::wire::{ClientMsg, IdRange, MAX_RANGES};
use tetwave_protocol::{BaseMesh, DetailNode};
use tokio::sync::mpsc;

/// The state of one streamed session's ingestion, around the [`Session`] its caller holds.
#[derive(Default)]
pub struct Ingest {
    manifest: Option<Manifest>,
    /// The level set's band when it comes before the base mesh.
    early_levelset: Option<NearLevelSet>,
    /// An answer about the band came, or none can come any more.
    levelset_answered: bool,
    levelset_error: Option<HttpError>,
    want_rounds: u32,
    ended: bool,
    max_nodes: u64,
}

/// What one delivery changed.
#[derive(Debug)]
pub enum Step {
    Manifest,
    /// A session was built on the base mesh.
    Started,
    /// The base mesh again (a resumed connection), or the end before any base mesh.
    Nothing,
    /// The band was set, or why it could not be had was recorded.
    LevelSet,
    /// A batch was inserted; its nodes are handed back.
    Nodes {
        nodes: Vec<DetailNode>,
        duplicates: usize,
    },
    /// A preview batch of `nodes` nodes was taken, `new` of them not held before.
    Preview {
        nodes: usize,
        new: usize,
    },
    /// The stream ended: everything is held ([`Ingest::ended`]) or what is missing was asked for.
    End,
}

impl Ingest {
    /// `max_nodes`: the largest hierarchy the client accepts (`--max-nodes`).
    pub fn new(max_nodes: u64) -> Self {
        Ingest {
            max_nodes,
            ..Default::default()
        }
    }

    pub fn manifest(&self) -> Option<&Manifest> {
        self.manifest.as_ref()
    }

    /// Every node has arrived and the server said so.
    pub fn ended(&self) -> bool {
        self.ended
    }

    /// Why drawn meshes are not clipped although the store has a level set.
    pub fn levelset_error(&self) -> Option<&HttpError> {
        self.levelset_error.as_ref()
    }

    /// The manifest lists a level set and no answer about it has come yet.
    pub fn levelset_pending(&self) -> bool {
        !self.levelset_answered
            && self
                .manifest
                .as_ref()
                .is_some_and(Manifest::has_levelset_band)
    }

    /// The network task has ended: no answer about the level set can come any more.
    pub fn network_ended(&mut self) {
        self.levelset_answered = true;
    }

    /// Applies one delivery to `session` (built by `start` on the base mesh, after the manifest
    /// and the client's limits have been checked). Re-requests go out on `out`. An error is the
    /// session's end; the caller decides whether the frames so far still count.
    pub fn apply(
        &mut self,
        delivery: Delivery,
        session: &mut Option<Session>,
        start: impl FnOnce(BaseMesh, &Manifest) -> Result<Session, NetError>,
        out: &mpsc::UnboundedSender<ClientMsg>,
    ) -> Result<Step, NetError> {
        Ok(match delivery {
            Delivery::Manifest(m) => {
                self.manifest = Some(*m);
                Step::Manifest
            }
            Delivery::Base(b) => match session {
                Some(s) if *s.base() == *b => Step::Nothing,
                Some(_) => return Err(NetError::BaseChanged),
                None => {
                    let m = self.manifest.as_ref().ok_or_else(|| NetError::OutOfOrder {
                        what: "base",
                        before: "manifest",
                    })?;
                    check_hierarchy(&b, m, self.max_nodes)?;
                    let mut s = start(*b, m)?;
                    if let Some(near) = self.early_levelset.take() {
                        s.set_levelset(near);
                    }
                    *session = Some(s);
                    Step::Started
                }
            },
            Delivery::LevelSet(got) => {
                self.levelset_answered = true;
                match got {
                    // (after a failed request, a reconnection asks again)
                    Ok(near) => {
                        self.levelset_error = None;
                        match session {
                            Some(s) => s.set_levelset(*near),
                            None => self.early_levelset = Some(*near),
                        }
                    }
                    // (an earlier request's failure, once a later one has brought the band)
                    Err(_)
                        if self.early_levelset.is_some()
                            || session.as_ref().is_some_and(Session::has_levelset) => {}
                    Err(e) => {
                        tracing::warn!("drawing without clipping to the domain's boundary: {e}");
                        self.levelset_error = Some(e);
                    }
                }
                Step::LevelSet
            }
            Delivery::Nodes { nodes, .. } => {
                let done = started(session, "nodes")?.insert(&nodes)?;
                Step::Nodes {
                    nodes,
                    duplicates: done.duplicates,
                }
            }
            Delivery::Preview { nodes, .. } => {
                let done = started(session, "preview")?.insert_preview(&nodes)?;
                Step::Preview {
                    nodes: nodes.len(),
                    new: done.new,
                }
            }
            Delivery::End => {
                // re-request whatever was lost on the way (bounded rounds); the missing ids are
                // walked as ranges, in time and memory of what arrived, whatever the hierarchy's
                // size
                let Some(s) = session.as_ref() else {
                    return Ok(Step::Nothing);
                };
                let (held, total) = s.progress();
                if held == total {
                    self.ended = true;
                } else if self.want_rounds < MAX_WANT_ROUNDS {
                    self.want_rounds += 1;
                    let want: Vec<IdRange> = s.buffer().missing_ranges().take(MAX_RANGES).collect();
                    let _ = out.send(ClientMsg::Want(want));
                } else {
                    return Err(NetError::Unavailable {
                        missing: total - held,
                        total,
                        rounds: self.want_rounds,
                    });
                }
                Step::End
            }
            Delivery::Error { code, message } => return Err(NetError::Server { code, message }),
        })
    }
}

/// The session, which `what` (nodes, a preview) needs: an error before the base mesh.
fn started<'s>(
    session: &'s mut Option<Session>,
    what: &'static str,
) -> Result<&'s mut Session, NetError> {
    session.as_mut().ok_or(NetError::OutOfOrder {
        what,
        before: "the base mesh",
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use tetwave_adaptive::select::{SelectParams, Tolerance};
    use tetwave_protocol::shapes::box5;
    use tetwave_protocol::store_format::{FileSum, LEVELSET_BAND_FILE};
    use tetwave_protocol::testing::{detail_nodes, manifest_for, unsampled_base};

    /// A two-level hierarchy with its nodes, and a manifest that agrees with it (listing a
    /// level-set band when `band`).
    fn data(band: bool) -> (BaseMesh, Vec<DetailNode>, Manifest) {
        let (base, nodes) = detail_nodes(unsampled_base(2, box5([0.0; 3], [1.0; 3])), |p| {
            (p[0] + 2.0 * p[1] * p[2]) as f32
        });
        let mut manifest = manifest_for(&base);
        if band {
            manifest.files.insert(
                LEVELSET_BAND_FILE.to_string(),
                FileSum { bytes: 1, crc32: 0 },
            );
        }
        (base, nodes, manifest)
    }

    fn start(b: BaseMesh, m: &Manifest) -> Result<Session, NetError> {
        Session::new(b, SelectParams::new(Tolerance::Pixels(0.0), m.value_range))
            .map_err(NetError::BaseMesh)
    }

    fn http_error(reason: &str) -> HttpError {
        HttpError {
            url: "http://127.0.0.1:1/v1/levelset".into(),
            reason: reason.into(),
        }
    }

    fn band() -> Box<NearLevelSet> {
        Box::new(NearLevelSet::new(0.25, [(0, -0.5), (1, 0.75)]).unwrap())
    }

    /// A client's ingestion, its session and its outgoing messages.
    struct Client {
        ingest: Ingest,
        session: Option<Session>,
        out: mpsc::UnboundedSender<ClientMsg>,
        sent: mpsc::UnboundedReceiver<ClientMsg>,
    }

    impl Client {
        fn new(max_nodes: u64) -> Self {
            let (out, sent) = mpsc::unbounded_channel();
            Client {
                ingest: Ingest::new(max_nodes),
                session: None,
                out,
                sent,
            }
        }
        fn give(&mut self, d: Delivery) -> Result<Step, NetError> {
            self.ingest.apply(d, &mut self.session, start, &self.out)
        }
        fn base(b: &BaseMesh) -> Delivery {
            Delivery::Base(Box::new(b.clone()))
        }
        fn nodes(nodes: &[DetailNode]) -> Delivery {
            Delivery::Nodes {
                seq: 0,
                nodes: nodes.to_vec(),
            }
        }
    }

    #[test]
    fn a_band_before_the_base_mesh_clips_the_session_it_starts() {
        let (base, _, m) = data(true);
        let mut c = Client::new(u64::MAX);
        c.give(Delivery::Manifest(Box::new(m))).unwrap();
        assert!(c.ingest.levelset_pending());
        let step = c.give(Delivery::LevelSet(Ok(band())));
        assert!(matches!(step, Ok(Step::LevelSet)));
        assert!(!c.ingest.levelset_pending() && c.session.is_none());
        let step = c.give(Client::base(&base));
        assert!(matches!(step, Ok(Step::Started)));
        assert!(c.session.as_ref().is_some_and(Session::has_levelset));
        // an earlier request's failure, arriving late, does not undo it
        c.give(Delivery::LevelSet(Err(http_error("gone")))).unwrap();
        assert_eq!(c.ingest.levelset_error(), None);
    }

    #[test]
    fn a_failed_band_is_reported_and_no_longer_awaited() {
        let (base, _, m) = data(true);
        let mut c = Client::new(u64::MAX);
        c.give(Delivery::Manifest(Box::new(m))).unwrap();
        c.give(Client::base(&base)).unwrap();
        assert!(c.ingest.levelset_pending());
        c.give(Delivery::LevelSet(Err(http_error("404")))).unwrap();
        assert_eq!(
            c.ingest.levelset_error().map(|e| e.reason.as_str()),
            Some("404")
        );
        assert!(!c.ingest.levelset_pending());
        assert!(!c.session.as_ref().unwrap().has_levelset());
        // a later success (after a reconnection) clears the failure
        c.give(Delivery::LevelSet(Ok(band()))).unwrap();
        assert_eq!(c.ingest.levelset_error(), None);
        assert!(c.session.as_ref().unwrap().has_levelset());
    }

    #[test]
    fn out_of_order_and_resumed_openings() {
        let (base, nodes, m) = data(false);
        let mut c = Client::new(u64::MAX);
        let before_manifest = c.give(Client::base(&base));
        assert!(matches!(before_manifest, Err(NetError::OutOfOrder { .. })));
        assert!(c.give(Client::nodes(&nodes)).is_err());
        assert!(!c.ingest.levelset_pending(), "no band listed");
        c.give(Delivery::Manifest(Box::new(m.clone()))).unwrap();
        // over the client's node limit: refused before any session exists
        let mut small = Client::new(1);
        small.give(Delivery::Manifest(Box::new(m))).unwrap();
        let too_large = small.give(Client::base(&base));
        assert!(matches!(too_large, Err(NetError::TooLarge { .. })));
        c.give(Client::base(&base)).unwrap();
        // a resumed connection's base mesh: the same one is kept, another one is refused
        let again = c.give(Client::base(&base));
        assert!(matches!(again, Ok(Step::Nothing)));
        let mut other = base;
        other.positions[0][0] -= 0.5;
        let other = c.give(Client::base(&other));
        assert!(matches!(other, Err(NetError::BaseChanged)));
        let server = c.give(Delivery::Error {
            code: 7,
            message: "bye".into(),
        });
        assert!(matches!(server, Err(NetError::Server { code: 7, .. })));
    }

    #[test]
    fn the_end_asks_for_what_is_missing_a_bounded_number_of_times() {
        let (base, nodes, m) = data(false);
        let mut c = Client::new(u64::MAX);
        c.give(Delivery::Manifest(Box::new(m))).unwrap();
        c.give(Client::base(&base)).unwrap();
        let (half, rest) = nodes.split_at(nodes.len() / 2);
        let step = c.give(Client::nodes(half)).unwrap();
        assert!(
            matches!(step, Step::Nodes { ref nodes, duplicates: 0 } if nodes.len() == half.len())
        );
        for _ in 0..MAX_WANT_ROUNDS {
            let step = c.give(Delivery::End);
            assert!(matches!(step, Ok(Step::End)));
            let Ok(ClientMsg::Want(want)) = c.sent.try_recv() else {
                panic!("a Want after an incomplete End")
            };
            let asked: u64 = want.iter().map(|r| r.to.saturating_sub(r.from)).sum();
            assert_eq!(asked, rest.len() as u64);
        }
        assert!(!c.ingest.ended());
        let gave_up = c.give(Delivery::End);
        assert!(matches!(
            gave_up,
            Err(NetError::Unavailable { missing, rounds: MAX_WANT_ROUNDS, .. })
                if missing == rest.len() as u64
        ));
        // the rest arrives (twice): the next End completes the stream
        for _ in 0..2 {
            c.give(Client::nodes(rest)).unwrap();
        }
        c.give(Delivery::End).unwrap();
        assert!(c.ingest.ended());
    }
}
