//! `pregrasp serve --demo`: built-in objects, a default gripper and a generated scene replayed
//! into the server itself, looping.

use super::AppState;

pub fn start(_state: AppState) -> anyhow::Result<()> {
    anyhow::bail!("the demo needs the scene generator (being merged)")
}
