//! Tools around the service that are no part of it: the replay client streams a recorded
//! sequence into a running server over HTTP, as a robot would. They talk to the service over
//! the network only, so they name neither `api` nor `service`.

pub mod replay;
