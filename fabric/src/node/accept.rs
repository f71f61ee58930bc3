//! Taking connections and opening them. Every connection starts with the handshake (the
//! cluster secret, the build, and who the caller claims to be); a claim this node does not
//! expect from the topology is refused before any frame of it is read, so that a stranger or
//! an impostor can neither displace a real link nor reach the role code.

use std::{net::SocketAddr, sync::Arc, time::Duration};

use protocol::{
    ConnectionKind, Frame, FrameReader, FrameWriter, Identity, Message, NodeId, Role, handshake,
};
use tokio::net::{TcpListener, TcpStream};

use super::{Delivery, Fabric, links::expected_direct, pending_handshakes_allowed};
use crate::topology::Topology;

/// Why a connection to a peer could not be made.
#[derive(Debug, thiserror::Error)]
pub enum DialError {
    #[error("cannot reach node {peer} at {addr}: {source}")]
    Unreachable {
        peer: NodeId,
        addr: String,
        source: std::io::Error,
    },
    #[error("node {peer} at {addr}: {source}")]
    Handshake {
        peer: NodeId,
        addr: String,
        source: handshake::HandshakeError,
    },
}

impl Fabric {
    /// Whether a peer may open a connection of this kind to us.
    fn accepts(&self, id: &Identity) -> bool {
        let inner = &self.inner;
        let connected = |kind: ConnectionKind, peer: NodeId| {
            inner.table(kind).lock().expect("lock").contains_key(&peer)
        };
        accepts(&inner.topology, inner.me, inner.role, id, connected)
    }

    /// Accepts connections forever: handshake, check the caller's claim, attach.
    pub(crate) fn serve(&self, listener: TcpListener) {
        let me = self.clone();
        // Only the host hears from every node at once; a node hears from its neighbours.
        let allowed = match self.inner.role {
            protocol::Role::Host => pending_handshakes_allowed(self.inner.topology.len()),
            _ => super::MAX_PENDING_HANDSHAKES,
        };
        let pending = Arc::new(tokio::sync::Semaphore::new(allowed));
        tokio::spawn(async move {
            loop {
                let (stream, addr) = match listener.accept().await {
                    Ok(x) => x,
                    Err(e) => {
                        tracing::warn!("accept failed: {e}");
                        tokio::time::sleep(Duration::from_millis(50)).await;
                        continue;
                    }
                };
                // Unauthenticated connections are bounded: beyond this many handshakes in
                // progress, new ones are closed at once.
                let Ok(permit) = pending.clone().try_acquire_owned() else {
                    me.inner.count(|c| &c.connections_refused);
                    tracing::warn!(
                        "refused a connection from {addr}: too many handshakes in progress"
                    );
                    continue;
                };
                let me = me.clone();
                tokio::spawn(async move {
                    me.answer(stream, addr).await;
                    drop(permit);
                });
            }
        });
    }

    async fn answer(&self, stream: TcpStream, addr: SocketAddr) {
        let _ = stream.set_nodelay(true);
        let (r, w) = stream.into_split();
        let mut reader = FrameReader::new(r);
        reader.frame_timeout = handshake::HANDSHAKE_TIMEOUT;
        let mut writer = FrameWriter::new(w);
        let identity = match handshake::answer(
            &mut reader,
            &mut writer,
            &self.inner.secret,
            &self.inner.cluster_id,
        )
        .await
        {
            Ok(i) => i,
            Err(e) => {
                self.inner.count(|c| &c.connections_refused);
                tracing::warn!("refused a connection from {addr}: {e}");
                return;
            }
        };
        if !self.accepts(&identity) {
            self.inner.count(|c| &c.connections_refused);
            tracing::warn!(
                "refused a connection from {addr}: it claims {identity:?}, which this node does not expect"
            );
            let reason = format!(
                "node {} does not take {:?} connections from {:?}",
                self.inner.me, identity.kind, identity.node
            );
            let _ = writer
                .write(&Frame::new(
                    self.inner.me,
                    0,
                    &Message::Refused { reason },
                    Box::new([]),
                ))
                .await;
            return;
        }
        match identity.node {
            Some(peer) => self.attach(peer, identity.kind, reader, writer),
            None => {
                let _ = self.inner.inbox.send(Delivery::Incoming {
                    identity,
                    reader,
                    writer,
                });
            }
        }
    }

    /// Dials `addr`, proves ourselves, and attaches the connection as `kind` to `peer`.
    pub async fn dial(
        &self,
        peer: NodeId,
        addr: &str,
        kind: ConnectionKind,
    ) -> Result<(), DialError> {
        let deadline = tokio::time::Instant::now() + Duration::from_secs(30);
        let mut delay = Duration::from_millis(20);
        let stream = loop {
            match TcpStream::connect(addr).await {
                Ok(s) => break s,
                Err(e) if tokio::time::Instant::now() < deadline => {
                    tracing::debug!("dialing node {peer} at {addr}: {e}; retrying");
                    tokio::time::sleep(delay).await;
                    delay = (delay * 2).min(Duration::from_millis(500));
                }
                Err(source) => {
                    return Err(DialError::Unreachable {
                        peer,
                        addr: addr.to_string(),
                        source,
                    });
                }
            }
        };
        let _ = stream.set_nodelay(true);
        let (r, w) = stream.into_split();
        let mut reader = FrameReader::new(r);
        let mut writer = FrameWriter::new(w);
        let identity = Identity {
            role: self.inner.role,
            node: Some(self.inner.me),
            kind,
        };
        handshake::call(
            &mut reader,
            &mut writer,
            &self.inner.secret,
            &self.inner.cluster_id,
            identity,
        )
        .await
        .map_err(|source| DialError::Handshake {
            peer,
            addr: addr.to_string(),
            source,
        })?;
        self.attach(peer, kind, reader, writer);
        Ok(())
    }
}

/// Whether node `me` (of `role`) takes a connection from a caller claiming `id`, given which
/// connections are already `connected`.
fn accepts(
    t: &Topology,
    me: NodeId,
    role: Role,
    id: &Identity,
    connected: impl Fn(ConnectionKind, NodeId) -> bool,
) -> bool {
    let Some(peer) = id.node else {
        // Only the host takes connections from nodes without an id (registration).
        return role == Role::Host && id.kind == ConnectionKind::Control;
    };
    if peer as usize >= t.len() || t.role(peer) != id.role || peer == me {
        return false;
    }
    // One connection of each kind per peer: a second claim to be a peer that is already
    // connected is an impostor (or a confused restart) and must not displace the first.
    let expected = match id.kind {
        ConnectionKind::Mesh => t.neighbors(me).contains(&peer),
        ConnectionKind::Direct => expected_direct(t, me).contains(&peer),
        ConnectionKind::Control => false,
    };
    expected && !connected(id.kind, peer)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn claim(role: Role, node: Option<NodeId>, kind: ConnectionKind) -> Identity {
        Identity { role, node, kind }
    }

    /// grid:2x1x1: host 0, fork nodes 1 and 2, render nodes 3 (card 0) and 4 (card 1).
    fn grid() -> Topology {
        Topology::preset("grid:2x1x1").unwrap()
    }

    const NONE: fn(ConnectionKind, NodeId) -> bool = |_, _| false;

    #[test]
    fn only_the_host_takes_registrations() {
        let t = grid();
        let register = claim(Role::Render, None, ConnectionKind::Control);
        assert!(accepts(&t, 0, Role::Host, &register, NONE));
        assert!(!accepts(&t, 1, Role::Fork, &register, NONE));
        let mesh_without_id = claim(Role::Render, None, ConnectionKind::Mesh);
        assert!(!accepts(&t, 0, Role::Host, &mesh_without_id, NONE));
    }

    #[test]
    fn links_the_topology_has_are_taken_once() {
        let t = grid();
        let from_4 = claim(Role::Render, Some(4), ConnectionKind::Mesh);
        assert!(accepts(&t, 3, Role::Render, &from_4, NONE));
        let already = |kind, peer| kind == ConnectionKind::Mesh && peer == 4;
        assert!(!accepts(&t, 3, Role::Render, &from_4, already));
        let direct_from_3 = claim(Role::Render, Some(3), ConnectionKind::Direct);
        assert!(accepts(&t, 1, Role::Fork, &direct_from_3, NONE));
        // A mesh link already up does not stop the direct connection.
        assert!(accepts(&t, 1, Role::Fork, &direct_from_3, already));
    }

    #[test]
    fn claims_the_topology_does_not_back_are_refused() {
        let t = grid();
        // Render node 4 is on the other card: no direct connection to fork node 1.
        let wrong_card = claim(Role::Render, Some(4), ConnectionKind::Direct);
        assert!(!accepts(&t, 1, Role::Fork, &wrong_card, NONE));
        // Node 3 is a render node, not a fork node.
        let wrong_role = claim(Role::Fork, Some(3), ConnectionKind::Mesh);
        assert!(!accepts(&t, 4, Role::Render, &wrong_role, NONE));
        let not_a_neighbour = claim(Role::Fork, Some(2), ConnectionKind::Mesh);
        assert!(!accepts(&t, 3, Role::Render, &not_a_neighbour, NONE));
        let myself = claim(Role::Render, Some(3), ConnectionKind::Mesh);
        assert!(!accepts(&t, 3, Role::Render, &myself, NONE));
        let no_such_node = claim(Role::Render, Some(99), ConnectionKind::Mesh);
        assert!(!accepts(&t, 3, Role::Render, &no_such_node, NONE));
        let control_with_id = claim(Role::Fork, Some(1), ConnectionKind::Control);
        assert!(!accepts(&t, 0, Role::Host, &control_with_id, NONE));
    }
}
