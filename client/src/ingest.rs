//! What the frame loop does with each message the network task delivers, shared by
//! `tetwave stream` and the viewer: keep the manifest, build the session on the base mesh (and
//! keep it when a resumed connection sends the same base again), set the level set's band
//! whether it comes before or after the base, insert node batches, and at the stream's end
//! re-request what is missing, a bounded number of times.

use crate::session::Session;
use crate::stream::{check_hierarchy, Delivery, StreamError, MAX_WANT_ROUNDS};
use tetwave_protocol::levelset::NearLevelSet;
use tetwave_protocol::store_format::Manifest;
use tetwave_protocol::wire::{ClientMsg, IdRange, MAX_RANGES};
use tetwave_protocol::{BaseMesh, DetailNode};
use tokio::sync::mpsc;

/// The state of one streamed session's ingestion, around the [`Session`] its caller holds.
#[derive(Default)]
pub(crate) struct Ingest {
    manifest: Option<Manifest>,
    /// The level set's band when it comes before the base mesh.
    early_levelset: Option<NearLevelSet>,
    /// An answer about the band came, or none can come any more.
    levelset_answered: bool,
    levelset_error: Option<String>,
    want_rounds: u32,
    ended: bool,
    max_nodes: u64,
}

/// What one delivery changed.
#[derive(Debug)]
pub(crate) enum Step {
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
    pub fn levelset_error(&self) -> Option<&str> {
        self.levelset_error.as_deref()
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
        start: impl FnOnce(BaseMesh, &Manifest) -> Result<Session, StreamError>,
        out: &mpsc::UnboundedSender<ClientMsg>,
    ) -> Result<Step, StreamError> {
        Ok(match delivery {
            Delivery::Manifest(m) => {
                self.manifest = Some(*m);
                Step::Manifest
            }
            Delivery::Base(b) => match session {
                Some(s) if *s.base() == *b => Step::Nothing,
                Some(_) => {
                    return Err(StreamError::Protocol(
                        "the server sent a different base mesh on a resumed connection".into(),
                    ))
                }
                None => {
                    let m = self
                        .manifest
                        .as_ref()
                        .ok_or_else(|| StreamError::Protocol("base before manifest".into()))?;
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
                let s = session
                    .as_mut()
                    .ok_or_else(|| StreamError::Protocol("nodes before the base mesh".into()))?;
                let done = s.insert(&nodes)?;
                Step::Nodes {
                    nodes,
                    duplicates: done.duplicates,
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
                    return Err(StreamError::Unavailable {
                        missing: total - held,
                        total,
                        rounds: self.want_rounds,
                    });
                }
                Step::End
            }
            Delivery::Error { code, message } => return Err(StreamError::Server { code, message }),
        })
    }
}
