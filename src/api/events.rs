//! `/events`: Server-Sent Events for the dashboard and for planners that prefer push. Each
//! event's `event:` name and `data:` JSON are one variant of [`ServerEvent`], documented in
//! the OpenAPI file: `track` (a [`TrackView`]), `decision` ([`DecisionEvent`]), `frame`
//! ([`FrameEvent`]), `stats` ([`Stats`]).

use super::AppState;
use super::decisions::DecisionView;
use super::tracks::TrackView;
use crate::service::events::{self as service_events, ServiceEvent};
use axum::extract::State;
use axum::response::sse::{Event, KeepAlive, Sse};
use futures::Stream;
use serde::{Deserialize, Serialize};
use std::convert::Infallible;
use tokio_stream::StreamExt;
use tokio_stream::wrappers::BroadcastStream;
use utoipa::openapi::schema::{ObjectBuilder, OneOfBuilder, Schema, Type};
use utoipa::openapi::{Ref, RefOr};
use utoipa::{PartialSchema, ToSchema};
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

/// Rates published once a second.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct Stats {
    pub step_rate_hz: f64,
    pub ingest_rate_hz: f64,
    pub queue_depth: usize,
    pub frames_stale: u64,
    pub frames_dropped: u64,
}

impl From<&service_events::Stats> for Stats {
    fn from(s: &service_events::Stats) -> Self {
        Self {
            step_rate_hz: s.step_rate_hz,
            ingest_rate_hz: s.ingest_rate_hz,
            queue_depth: s.queue_depth,
            frames_stale: s.frames_stale,
            frames_dropped: s.frames_dropped,
        }
    }
}

/// A decision answered for a track (the `decision` event's data).
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct DecisionEvent {
    pub track_id: u64,
    pub decision: DecisionView,
}

/// A frame accepted from a camera (the `frame` event's data).
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct FrameEvent {
    pub camera: String,
    pub stamp_ns: i64,
}

/// One event of the stream: `event` is the SSE event name, `data` its JSON (see the schema
/// below, written by hand: SSE carries `data` as a string of JSON).
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(tag = "event", content = "data", rename_all = "snake_case")]
pub enum ServerEvent {
    Track(Box<TrackView>),
    Decision(Box<DecisionEvent>),
    Frame(FrameEvent),
    Stats(Stats),
}

/// The event names with the schemas of their data.
const EVENT_DATA: [(&str, &str); 4] = [
    ("track", "TrackView"),
    ("decision", "DecisionEvent"),
    ("frame", "FrameEvent"),
    ("stats", "Stats"),
];

/// Each event as an SSE client reads it (OpenAPI 3.2's way for `text/event-stream`): the
/// `event` name, and `data`, a string of JSON whose schema is `contentSchema`.
impl utoipa::PartialSchema for ServerEvent {
    fn schema() -> RefOr<Schema> {
        let variant = |name: &str, data: &str| {
            ObjectBuilder::new()
                .property(
                    "event",
                    ObjectBuilder::new().schema_type(Type::String).enum_values(Some([name])),
                )
                .property(
                    "data",
                    ObjectBuilder::new()
                        .schema_type(Type::String)
                        .content_media_type("application/json")
                        .content_schema(Some(Ref::from_schema_name(data))),
                )
                .required("event")
                .required("data")
        };
        let mut one_of = OneOfBuilder::new().description(Some(
            "One event of the stream: its SSE event name and its data, a string of JSON",
        ));
        for (name, data) in EVENT_DATA {
            one_of = one_of.item(variant(name, data));
        }
        one_of.into()
    }
}

impl ToSchema for ServerEvent {
    fn schemas(schemas: &mut Vec<(String, RefOr<Schema>)>) {
        schemas.push((TrackView::name().into(), TrackView::schema()));
        <TrackView as ToSchema>::schemas(schemas);
        schemas.push((DecisionEvent::name().into(), DecisionEvent::schema()));
        <DecisionEvent as ToSchema>::schemas(schemas);
        schemas.push((FrameEvent::name().into(), FrameEvent::schema()));
        schemas.push((Stats::name().into(), Stats::schema()));
    }
}

impl From<&ServiceEvent> for ServerEvent {
    fn from(e: &ServiceEvent) -> Self {
        match e {
            ServiceEvent::Track(t) => Self::Track(Box::new(TrackView::from(&**t))),
            ServiceEvent::Decision { track_id, decision } => Self::Decision(Box::new(DecisionEvent {
                track_id: *track_id,
                decision: DecisionView::from(&**decision),
            })),
            ServiceEvent::Frame { camera, stamp_ns } => Self::Frame(FrameEvent {
                camera: camera.clone(),
                stamp_ns: *stamp_ns,
            }),
            ServiceEvent::Stats(s) => Self::Stats(s.into()),
        }
    }
}

impl ServerEvent {
    fn to_sse(&self) -> Event {
        let (name, data) = match self {
            Self::Track(v) => ("track", serde_json::to_string(v)),
            Self::Decision(d) => ("decision", serde_json::to_string(d)),
            Self::Frame(f) => ("frame", serde_json::to_string(f)),
            Self::Stats(s) => ("stats", serde_json::to_string(s)),
        };
        Event::default().event(name).data(data.unwrap_or_default())
    }
}

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new().routes(routes!(events))
}

#[utoipa::path(get, path = "/events", tag = "events",
    responses((status = 200, description = "text/event-stream of track, decision, frame and stats events; each event's name and data JSON as in ServerEvent", content_type = "text/event-stream", body = ServerEvent)))]
async fn events(State(state): State<AppState>) -> Sse<impl Stream<Item = Result<Event, Infallible>>> {
    // A slow client misses events (lagged) rather than holding memory.
    let mut shutdown = state.shutting_down.subscribe();
    let events = BroadcastStream::new(state.events.subscribe())
        .filter_map(|e| e.ok().map(|e| Ok(ServerEvent::from(&e).to_sse())));
    let stream = futures::StreamExt::take_until(events, async move {
        let _ = shutdown.wait_for(|v| *v).await;
    });
    Sse::new(stream).keep_alive(KeepAlive::default())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_documented_event_names_are_the_sent_ones() {
        let events = [
            ServerEvent::Frame(FrameEvent {
                camera: "ext1".into(),
                stamp_ns: 1,
            }),
            ServerEvent::Stats(Stats::default()),
        ];
        for (e, schema) in events.iter().zip(["FrameEvent", "Stats"]) {
            let v = serde_json::to_value(e).unwrap();
            let name = v["event"].as_str().unwrap();
            assert!(EVENT_DATA.contains(&(name, schema)), "{name}");
        }
        let doc = serde_json::to_value(ServerEvent::schema()).unwrap();
        let names: Vec<&str> = doc["oneOf"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v["properties"]["event"]["enum"][0].as_str().unwrap())
            .collect();
        assert_eq!(names, ["track", "decision", "frame", "stats"]);
    }
}
