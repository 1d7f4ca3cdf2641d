//! The daemon serving a contract-v2 variant beside contract-v1 ones and a variant named
//! after its directory: models listing, automatic and named choice, per-stage timings,
//! refusals.

use crate::common;
use crate::daemon_common;
use crate::model_dirs;

use hyper::StatusCode;

use common::{exr_single, named_planes, Sample};
use daemon_common::*;
use model_dirs::mixed;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn v2_and_named_variants_are_served_like_v1() {
    let dir = tempfile::tempdir().unwrap();
    let models = mixed();
    let models_arg = models.path().display().to_string();
    let d = start(dir.path(), &["--models", &models_arg, "--tile-v2", "16", "--debug-tile-delay", "30ms"]).await;
    d.ready().await;

    let (status, listing) = d.get_json("/v1/models").await;
    assert_eq!(status, StatusCode::OK);
    let rows: Vec<(String, String, String)> = listing["models"]
        .as_array()
        .unwrap()
        .iter()
        .map(|m| {
            let s = |k: &str| m[k].as_str().unwrap().to_string();
            (s("variant"), s("component"), s("contract"))
        })
        .collect();
    let want = [
        ("full", "both", "2"),
        ("lin2020", "diffuse", "1"),
        ("lin2020", "specular", "1"),
        ("nocov", "diffuse", "1"),
        ("nocov", "specular", "1"),
    ];
    assert_eq!(rows, want.map(|(a, b, c)| (a.to_string(), b.to_string(), c.to_string())));

    let (w, h) = (40, 36);
    let with_cov = exr_single(w, h, &named_planes(w, h, true), Sample::F32);
    let without = frame(w, h);

    // Automatic: `full` (contract v2) for a frame with covariance, with its stage timings.
    let id = d.submit_ok(&with_cov, "").await;
    let job = d.wait_state(&id, "succeeded").await;
    assert_eq!(job["variant"], "full");
    let tiles = &job["progress"];
    assert!(tiles["tiles_total"].as_u64().unwrap() >= 4, "{tiles}");
    for stage in ["preprocess", "inference", "reconstruction"] {
        assert!(job["timings_ms"][stage].as_f64().unwrap() > 0.0, "{stage}: {}", job["timings_ms"]);
    }
    let (status, body) = d.result(&id).await;
    assert_eq!(status, StatusCode::OK);
    assert!(!body.is_empty());

    // A running job's tile count is that of its model's contract from the start.
    let id = d.submit_ok(&with_cov, "variant=full").await;
    let running = d.wait_running(&id).await;
    let done = d.wait_state(&id, "succeeded").await;
    assert_eq!(running["progress"]["tiles_total"], done["progress"]["tiles_total"], "{running}\n{done}");

    // Named: lin2020 for a frame with covariance; refused at run time without it.
    let id = d.submit_ok(&with_cov, "variant=lin2020").await;
    let job = d.wait_state(&id, "succeeded").await;
    assert_eq!((job["variant"].as_str(), job["requested_variant"].as_str()), (Some("lin2020"), Some("lin2020")));
    let id = d.submit_ok(&without, "variant=lin2020").await;
    let job = d.wait_state(&id, "failed").await;
    assert_eq!(job["error"]["code"], "no_model", "{job}");
    assert!(job["error"]["message"].as_str().unwrap().contains("needs a `covariance` channel"), "{job}");

    // A variant that is not loaded is refused at submission, naming the loaded ones.
    let (status, err) = d.submit(&with_cov, "variant=oidn", &[]).await;
    assert_eq!(status, StatusCode::BAD_REQUEST);
    assert_eq!(err["error"]["message"], "no `oidn` model is loaded (loaded: full, lin2020, nocov)");
    d.stop().await;
}
