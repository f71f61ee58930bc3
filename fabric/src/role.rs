//! The life every node role shares, written once: join the cluster, take deliveries in
//! order, answer diagnostics, obey the host's shutdown and node-down notices, leave.
//!
//! The fork node and the render node differ only in what they do with the rest of their
//! messages; each says that in a [`RoleHandler`]. Keeping the loop here means a change to
//! how nodes stop, or to what counts as losing the host, is made for both roles at once.

use protocol::{ConnectionKind, Frame, Message};

use crate::{
    Delivery, Fabric, Via,
    cluster::{ClusterError, JoinConfig, join, leave},
};

/// How long a lost connection to another node waits to be explained by the host's shutdown
/// before it is logged as a warning.
const SHUTDOWN_GRACE: std::time::Duration = std::time::Duration::from_secs(1);

/// Why a node role ended other than by the host's shutdown.
#[derive(Debug, thiserror::Error)]
pub enum RoleError {
    #[error("joining the cluster: {0}")]
    Join(#[from] ClusterError),
    #[error("lost the connection to the host")]
    HostLost,
}

/// What a role does with the messages the shared loop leaves to it.
pub trait RoleHandler {
    /// How the role names itself in the log ("fork node"), so that every line about the
    /// shared life reads the same as the role's own.
    const NAME: &'static str;

    /// A decoded message that is neither a diagnostic nor the host's shutdown or node-down
    /// notice. Runs on the node's runtime, so it may spawn tasks but must not block.
    fn on_message(&mut self, frame: Frame, message: Message, via: Via);
}

/// Joins the cluster, builds the role's handler from the joined fabric, and runs it until
/// the host says stop (`Ok`, also before the cluster formed) or goes away
/// (`Err(RoleError::HostLost)`).
pub async fn run_role<H: RoleHandler>(
    config: JoinConfig,
    make_handler: impl FnOnce(&Fabric) -> H,
) -> Result<(), RoleError> {
    let name = H::NAME;
    let joined = match join(config).await {
        Ok(joined) => joined,
        // The host waits for this node to hang up before it exits, so there is no leaving
        // to do: the stop is obeyed as one after the cluster formed is.
        Err(ClusterError::StoppedByHost { node, reason }) => {
            tracing::info!("{name} {node} stopping: {reason}");
            return Ok(());
        }
        Err(e) => return Err(e.into()),
    };
    let fabric = joined.fabric.clone();
    let mut inbox = joined.inbox;
    let mut handler = make_handler(&fabric);
    tracing::info!("{name} {} ready", fabric.me());
    // What arrived before the host said go comes first, in the order it arrived.
    let mut early = std::collections::VecDeque::from(joined.early);
    // A neighbour that read the host's shutdown first hangs up before this node has read
    // its own: such losses are told only if no shutdown follows within the grace.
    let mut unexplained: std::collections::VecDeque<(tokio::time::Instant, String)> =
        Default::default();
    loop {
        let delivery = match early.pop_front() {
            Some(d) => d,
            None => {
                let next = match unexplained.front() {
                    Some(&(deadline, _)) => {
                        match tokio::time::timeout_at(deadline, inbox.recv()).await {
                            Ok(next) => next,
                            Err(_) => {
                                if let Some((_, line)) = unexplained.pop_front() {
                                    tracing::warn!("{line}");
                                }
                                continue;
                            }
                        }
                    }
                    None => inbox.recv().await,
                };
                match next {
                    Some(d) => d,
                    None => return Err(RoleError::HostLost),
                }
            }
        };
        match delivery {
            Delivery::Frame { frame, via } => {
                let message = match frame.message() {
                    Ok(m) => m,
                    Err(e) => {
                        tracing::warn!("undecodable frame from node {}: {e}", frame.header.sender);
                        continue;
                    }
                };
                if crate::diag::handle(&fabric, &frame, &message) {
                    continue;
                }
                // Only the host, on its control connection, may stop this node or declare
                // another dead; the same messages by any other way go to the role, which
                // ignores them.
                match (&message, via) {
                    (Message::Shutdown { reason }, Via::Control(0)) => {
                        for (_, line) in unexplained.drain(..) {
                            tracing::debug!("{line} (the cluster is stopping)");
                        }
                        tracing::info!("{name} {} stopping: {reason}", fabric.me());
                        leave(&fabric).await;
                        return Ok(());
                    }
                    (Message::NodeDown { node }, Via::Control(0)) => {
                        tracing::warn!(
                            "{name} {}: node {node} is gone; routing around it",
                            fabric.me()
                        );
                        fabric.mark_dead(*node);
                    }
                    _ => handler.on_message(frame, message, via),
                }
            }
            Delivery::Lost {
                peer: 0,
                kind: ConnectionKind::Control,
                ..
            } => {
                tracing::error!("{name} {}: lost the host; exiting", fabric.me());
                fabric.begin_shutdown();
                return Err(RoleError::HostLost);
            }
            Delivery::Lost { peer, kind, reason } => unexplained.push_back((
                tokio::time::Instant::now() + SHUTDOWN_GRACE,
                format!(
                    "{name} {}: lost {kind:?} connection to node {peer}: {reason}",
                    fabric.me()
                ),
            )),
            Delivery::Incoming { .. } => {}
        }
    }
}
