//! A cluster forms inside one test process (each node its own fabric, over real loopback
//! TCP): registration, links, routing of one-to-one and broadcast frames.

use std::time::Duration;

use fabric::{
    Delivery, Topology, Via,
    cluster::{JoinConfig, form, join},
};
use protocol::{Message, Role, Secret};
use tokio::net::TcpListener;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tiny_cluster_forms_and_routes() {
    let topology = Topology::preset("tiny").unwrap();
    let secret = Secret::new("test secret 123").unwrap();
    let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap().to_string();
    let mut joins = Vec::new();
    let (f, r) = topology.counts();
    for role in std::iter::repeat_n(Role::Fork, f).chain(std::iter::repeat_n(Role::Render, r)) {
        let cfg = JoinConfig {
            host: addr.clone(),
            listen: "127.0.0.1:0".into(),
            advertise: None,
            role,
            secret: secret.clone(),
            cluster_id: "magg".into(),
            timeout: Duration::from_secs(20),
        };
        joins.push(tokio::spawn(join(cfg)));
    }
    let formed = form(
        listener,
        topology.clone(),
        secret.clone(),
        "magg",
        Duration::from_secs(20),
        &|_, _| {},
        false,
        std::future::pending(),
    )
    .await;
    let mut nodes = Vec::new();
    for j in joins {
        nodes.push(j.await.unwrap().unwrap());
    }
    let formed = formed.unwrap();
    assert_eq!(formed.members.len(), topology.len() - 1);

    // One-to-one from the host to every node, through the mesh.
    let host = formed.fabric.clone();
    let mut host_inbox = formed.inbox;
    for n in 1..topology.len() as u16 {
        host.send(
            n,
            // Any message but a heartbeat: links swallow those.
            &Message::StatsRequest,
            vec![n as u32; 3].into_boxed_slice(),
            n as u32,
        )
        .unwrap();
    }
    for node in nodes.iter_mut() {
        let d = tokio::time::timeout(Duration::from_secs(5), node.inbox.recv())
            .await
            .unwrap()
            .unwrap();
        let Delivery::Frame {
            frame,
            via: Via::Mesh(_),
        } = d
        else {
            panic!("{d:?}")
        };
        assert_eq!(frame.header.receiver, node.node);
        assert_eq!(frame.header.tag, node.node as u32);
        assert_eq!(&frame.data[..], &[node.node as u32; 3]);
    }
    // A broadcast from a render node reaches every other node exactly once.
    let last = nodes.last().unwrap().fabric.clone();
    last.broadcast(&Message::Go, Box::new([]));
    let mut got = 0;
    for node in nodes.iter_mut().filter(|n| n.node != last.me()) {
        let d = tokio::time::timeout(Duration::from_secs(5), node.inbox.recv())
            .await
            .unwrap()
            .unwrap();
        assert!(matches!(d, Delivery::Frame { .. }));
        got += 1;
        assert!(
            tokio::time::timeout(Duration::from_millis(100), node.inbox.recv())
                .await
                .is_err(),
            "duplicate broadcast"
        );
    }
    let d = tokio::time::timeout(Duration::from_secs(5), host_inbox.recv())
        .await
        .unwrap()
        .unwrap();
    assert!(matches!(d, Delivery::Frame { .. }));
    assert_eq!(got, topology.len() - 2);
}
