//! Starting the rendering threads. A render node learns the scene header, the job and (for a
//! batch job) the data in whatever order they come; whichever completes the set starts
//! rendering, once. Whether to start is decided from what has arrived alone ([`decide`]),
//! apart from building the cache and the threads, so that the decision can be tested
//! without a cluster.

use std::sync::Arc;

use fabric::Fabric;
use protocol::{DataId, DmaTransport, JobSpec, NodeId, Transfer, TransferMode};
use renderer::SceneHeader;

use crate::{
    cache::{DemandCache, Source},
    shared::SharedSegments,
    worker::{ActiveMap, WorkStats, Worker},
};

/// What this node knows of the current render.
#[derive(Default)]
pub(crate) struct Render {
    pub scene: Option<Arc<SceneHeader>>,
    pub chunk_owner: Vec<NodeId>,
    pub tile_owner: Vec<NodeId>,
    pub job: Option<Arc<JobSpec>>,
    /// Batch data received before rendering starts, and how much is coming.
    pub batch: Vec<(DataId, Box<[u32]>)>,
    pub batch_expected: Option<u32>,
    pub cache: Option<Arc<DemandCache>>,
    pub started: bool,
    /// Cards' memories mapped on this machine, as their fork nodes announce them.
    pub segments: Arc<SharedSegments>,
}

/// Everything rendering needs, all here.
pub(crate) struct Ready {
    pub scene: Arc<SceneHeader>,
    pub job: Arc<JobSpec>,
    /// This card's fork node, which serves the data and forwards the pixels.
    pub fork: NodeId,
}

/// Why this render cannot start; the host is told and the node renders nothing.
#[derive(Debug, thiserror::Error)]
pub(crate) enum StartError {
    #[error(
        "the cache budget of {budget} bytes is smaller than the largest chunk ({largest} bytes)"
    )]
    CacheTooSmall { budget: u64, largest: u64 },
    #[error("batch data {id:?}: {source}")]
    Batch {
        id: DataId,
        #[source]
        source: renderer::DataError,
    },
}

/// Whether rendering can start now: `Ok(None)` while something is still to come (or
/// rendering has begun already). `fork` is this node's fork node, if the topology gives one.
pub(crate) fn decide(r: &Render, fork: Option<NodeId>) -> Result<Option<Ready>, StartError> {
    if r.started {
        return Ok(None);
    }
    let (Some(scene), Some(job), Some(fork)) = (&r.scene, &r.job, fork) else {
        return Ok(None);
    };
    match job.transfer {
        TransferMode::Demand => {
            // A chunk larger than the whole cache could never be fetched: the render would
            // hang on it, so it is refused before it starts.
            let largest = scene.largest_chunk_memory();
            if largest > job.cache_bytes {
                return Err(StartError::CacheTooSmall {
                    budget: job.cache_bytes,
                    largest,
                });
            }
        }
        TransferMode::Batch => {
            if r.batch_expected != Some(r.batch.len() as u32) {
                return Ok(None);
            }
        }
    }
    Ok(Some(Ready {
        scene: scene.clone(),
        job: job.clone(),
        fork,
    }))
}

/// The cache rendering reads: filled on demand from the fork node, or (batch) from the data
/// already here, which it takes out of `r`.
pub(crate) fn build_cache(
    fabric: &Fabric,
    r: &mut Render,
    ready: &Ready,
) -> Result<DemandCache, StartError> {
    let scene = &ready.scene;
    match ready.job.transfer {
        TransferMode::Demand => {
            let source = Source {
                fabric: fabric.clone(),
                runtime: tokio::runtime::Handle::current(),
                fork: ready.fork,
                chunk_owner: r.chunk_owner.clone(),
                tile_owner: r.tile_owner.clone(),
                via: ready.job.demand_via,
                shared: (ready.job.demand_via == Transfer::Dma
                    && ready.job.dma_transport == DmaTransport::Auto)
                    .then(|| r.segments.clone()),
            };
            Ok(DemandCache::new(
                scene.chunk_rules(),
                scene.tile_count as usize,
                ready.job.cache_bytes,
                Some(source),
            ))
        }
        TransferMode::Batch => {
            let cache = DemandCache::new(
                scene.chunk_rules(),
                scene.tile_count as usize,
                u64::MAX,
                None,
            );
            for (id, words) in r.batch.drain(..) {
                cache
                    .preload(id, words)
                    .map_err(|source| StartError::Batch { id, source })?;
            }
            Ok(cache)
        }
    }
}

/// Starts the job's rendering threads over `cache`; each reports its own failure to the
/// host. Nothing waits for them: they end when the host has no more work, or with the
/// process.
pub(crate) fn spawn_workers(
    fabric: &Fabric,
    ready: Ready,
    cache: Arc<DemandCache>,
    active: &ActiveMap,
    stats: &Arc<WorkStats>,
) {
    for t in 0..ready.job.render_threads.max(1) {
        let worker = Worker {
            fabric: fabric.clone(),
            runtime: tokio::runtime::Handle::current(),
            scene: ready.scene.clone(),
            job: ready.job.clone(),
            cache: cache.clone(),
            fork: ready.fork,
            active: active.clone(),
            stats: stats.clone(),
        };
        let f = fabric.clone();
        std::thread::Builder::new()
            .name(format!("render-{t}"))
            .spawn(move || {
                if let Err(e) = worker.run() {
                    crate::fail(&f, &e.to_string());
                }
            })
            .expect("spawn a rendering thread");
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scene() -> Arc<SceneHeader> {
        let opts = renderer::PrepareOptions {
            chunk_triangles: 64,
        };
        Arc::new(renderer::prepare(renderer::demo::demo_scene(), &opts).0)
    }

    fn job(transfer: TransferMode, cache_bytes: u64) -> Arc<JobSpec> {
        Arc::new(JobSpec {
            settings: renderer::RenderSettings::default(),
            camera: renderer::demo::demo_scene().cameras[0].clone(),
            transfer,
            demand_via: Transfer::Dma,
            dma_transport: DmaTransport::Auto,
            cache_bytes,
            render_threads: 1,
            coherent_rays: protocol::CoherentRays::Off,
            ask_ahead: false,
            ask_via: protocol::AskVia::Mesh,
        })
    }

    fn waits(r: &Render, fork: Option<NodeId>) -> bool {
        matches!(decide(r, fork), Ok(None))
    }

    #[test]
    fn waits_for_the_header_the_job_and_a_fork_node() {
        let scene = scene();
        let mut r = Render::default();
        assert!(waits(&r, Some(1)));
        r.job = Some(job(TransferMode::Demand, u64::MAX));
        assert!(waits(&r, Some(1)), "no header yet");
        r.scene = Some(scene);
        assert!(waits(&r, None), "no fork node");
        let ready = decide(&r, Some(1)).unwrap().expect("ready");
        assert_eq!(ready.fork, 1);
    }

    #[test]
    fn starts_only_once() {
        let r = Render {
            scene: Some(scene()),
            job: Some(job(TransferMode::Demand, u64::MAX)),
            started: true,
            ..Render::default()
        };
        assert!(waits(&r, Some(1)));
    }

    #[test]
    fn demand_refuses_a_cache_smaller_than_the_largest_chunk() {
        let scene = scene();
        let largest = scene.largest_chunk_memory();
        let mut r = Render {
            scene: Some(scene),
            job: Some(job(TransferMode::Demand, largest - 1)),
            ..Render::default()
        };
        match decide(&r, Some(1)) {
            Err(StartError::CacheTooSmall { budget, largest: l }) => {
                assert_eq!((budget, l), (largest - 1, largest))
            }
            other => panic!("expected a refusal, got {:?}", other.map(|r| r.is_some())),
        }
        r.job = Some(job(TransferMode::Demand, largest));
        assert!(
            decide(&r, Some(1)).unwrap().is_some(),
            "exactly the largest fits"
        );
    }

    #[test]
    fn batch_waits_for_every_announced_item() {
        let mut r = Render {
            scene: Some(scene()),
            job: Some(job(TransferMode::Batch, 0)),
            ..Render::default()
        };
        assert!(waits(&r, Some(1)), "nothing announced yet");
        r.batch_expected = Some(2);
        r.batch.push((DataId::Tile(0), Box::new([])));
        assert!(waits(&r, Some(1)), "one of two");
        r.batch.push((DataId::Tile(1), Box::new([])));
        assert!(decide(&r, Some(1)).unwrap().is_some());
    }
}
