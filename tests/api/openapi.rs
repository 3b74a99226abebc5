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

/// Whether a schema is a bare object: `{"type": "object"}` with nothing that says what is in it.
fn is_untyped_object(schema: &serde_json::Value) -> bool {
    let Some(o) = schema.as_object() else {
        return false;
    };
    let is_object = o
        .get("type")
        .is_some_and(|t| t == "object" || t.as_array().is_some_and(|a| a.iter().any(|x| x == "object")));
    let described = [
        "properties",
        "additionalProperties",
        "oneOf",
        "anyOf",
        "allOf",
        "$ref",
        "enum",
    ]
    .iter()
    .any(|k| o.contains_key(*k));
    is_object && !described
}

/// Every schema nested in `v` (a schema, a response, a component), with its JSON path.
fn schemas_in<'a>(v: &'a serde_json::Value, path: String, out: &mut Vec<(String, &'a serde_json::Value)>) {
    match v {
        serde_json::Value::Object(o) => {
            out.push((path.clone(), v));
            for (k, x) in o {
                schemas_in(x, format!("{path}/{k}"), out);
            }
        }
        serde_json::Value::Array(a) => {
            for (i, x) in a.iter().enumerate() {
                schemas_in(x, format!("{path}/{i}"), out);
            }
        }
        _ => {}
    }
}

/// Every answer of the document has a type: no response or component schema is a bare
/// `{"type": "object"}`, every JSON answer names its schema, and every error answer (4xx, 5xx)
/// is a problem document (`application/problem+json` with the `Problem` schema).
#[test]
fn every_answer_is_typed_and_every_error_a_problem_document() {
    let doc = serde_json::to_value(pregrasp::api::openapi()).expect("openapi json");
    let mut found = Vec::new();
    schemas_in(&doc["components"]["schemas"], "components/schemas".into(), &mut found);
    let mut n_errors = 0;
    let mut n_answers = 0;
    for (path, item) in doc["paths"].as_object().expect("paths") {
        for (method, op) in item.as_object().expect("path item") {
            // a path parameter is a segment of the path, everything else is in the query
            for param in op.get("parameters").and_then(|p| p.as_array()).into_iter().flatten() {
                let (name, place) = (param["name"].as_str().expect("name"), &param["in"]);
                let in_path = path.contains(&format!("{{{name}}}"));
                assert_eq!(
                    place == "path",
                    in_path,
                    "{method} {path}: parameter {name} is in {place}"
                );
            }
            let Some(responses) = op.get("responses").and_then(|r| r.as_object()) else {
                continue;
            };
            for (status, response) in responses {
                let content = response.get("content").and_then(|c| c.as_object());
                let here = format!("{method} {path} {status}");
                // required by OpenAPI 3.1 (client generators refuse a document without)
                assert!(
                    response["description"].as_str().is_some_and(|d| !d.is_empty()),
                    "{here}: no description"
                );
                if status.starts_with('4') || status.starts_with('5') {
                    n_errors += 1;
                    let content = content.unwrap_or_else(|| panic!("{here}: an error answer without content"));
                    let keys: Vec<&String> = content.keys().collect();
                    assert_eq!(keys, ["application/problem+json"], "{here}: {keys:?}");
                    assert_eq!(
                        content["application/problem+json"]["schema"]["$ref"], "#/components/schemas/Problem",
                        "{here}"
                    );
                    continue;
                }
                for (media, c) in content.into_iter().flatten() {
                    n_answers += 1;
                    if media.contains("json") || media == "text/event-stream" {
                        assert!(c.get("schema").is_some(), "{here} {media}: no schema");
                    }
                    schemas_in(c, format!("{here} {media}"), &mut found);
                }
            }
        }
    }
    assert!(
        n_errors > 50 && n_answers > 20,
        "{n_errors} errors, {n_answers} answers"
    );
    let untyped: Vec<&String> = found
        .iter()
        .filter(|(_, s)| is_untyped_object(s))
        .map(|(p, _)| p)
        .collect();
    assert!(untyped.is_empty(), "untyped objects: {untyped:?}");
    // the answers named in the issue have schemas of their own
    let schemas = doc["components"]["schemas"].as_object().expect("schemas");
    for name in [
        "DecisionView",
        "Reason",
        "RankedGrasp",
        "GripperDto",
        "ServerEvent",
        "DecisionEvent",
        "Problem",
    ] {
        assert!(schemas.contains_key(name), "no schema {name}");
    }
    let decision = &doc["paths"]["/api/v1/tracks/{id}/decision"]["post"]["responses"]["200"]["content"]["application/json"]
        ["schema"];
    assert_eq!(decision["$ref"], "#/components/schemas/DecisionView");
    let view = &schemas["DecisionView"]["properties"];
    for field in [
        "stamp_ns",
        "reference_from_gripper",
        "base_from_gripper",
        "world_from_gripper",
    ] {
        assert!(view.get(field).is_some(), "DecisionView has no {field}");
    }
    // the checker sees a bare object
    assert!(is_untyped_object(&serde_json::json!({"type": "object"})));
    assert!(!is_untyped_object(
        &serde_json::json!({"type": "object", "properties": {}})
    ));
}
