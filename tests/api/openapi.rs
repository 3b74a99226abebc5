//! The OpenAPI file in the repository must be what the code generates.
//! Regenerate with `UPDATE_OPENAPI=1 cargo test --test api openapi`.

use crate::spawn_app;
use std::path::Path;

#[tokio::test]
async fn openapi_file_matches_the_code() {
    let generated = serde_json::to_value(pregrasp::api::openapi()).expect("openapi json");
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("openapi/openapi.json");
    if std::env::var_os("UPDATE_OPENAPI").is_some() {
        let text = serde_json::to_string_pretty(&generated).expect("pretty") + "\n";
        std::fs::write(&path, text).expect("write openapi.json");
    }
    let on_disk: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&path).expect("read openapi/openapi.json"))
            .expect("parse openapi/openapi.json");
    assert!(
        on_disk == generated,
        "openapi/openapi.json is out of date: run UPDATE_OPENAPI=1 cargo test --test api openapi"
    );
    assert!(generated["openapi"].as_str().is_some_and(|v| v.starts_with("3.1")));
    for p in [
        "/api/v1/cameras/{id}",
        "/api/v1/cameras/{id}/frames",
        "/api/v1/tracks",
        "/api/v1/scene",
        "/healthz",
    ] {
        assert!(generated["paths"].get(p).is_some(), "missing path {p}");
    }

    // The served document is the same one.
    let app = spawn_app().await;
    let served: serde_json::Value = app
        .client
        .get(app.url("/openapi.json"))
        .send()
        .await
        .expect("get")
        .json()
        .await
        .expect("json");
    assert_eq!(served, generated);
    let docs = app.client.get(app.url("/docs/")).send().await.expect("docs");
    assert!(docs.status().is_success(), "swagger ui at /docs/: {}", docs.status());

    // The dashboard is served at / with its files.
    let index = app.client.get(app.url("/")).send().await.expect("index");
    assert!(
        index.headers()["content-type"]
            .to_str()
            .expect("ct")
            .starts_with("text/html")
    );
    assert!(index.text().await.expect("html").contains("app.js"));
    let js = app.client.get(app.url("/app.js")).send().await.expect("app.js");
    assert_eq!(js.status(), 200);
    assert!(
        js.headers()["content-type"]
            .to_str()
            .expect("ct")
            .starts_with("text/javascript")
    );
}
