//! Session ids: 1 to [`MAX_ID_BYTES`] bytes; an empty id asks for a fresh one.

use crate::Error;

/// Longest accepted session id, in bytes.
pub const MAX_ID_BYTES: usize = 128;

/// Session ids are 1 to [`MAX_ID_BYTES`] bytes (INVALID_ARGUMENT otherwise).
pub fn check_id(id: &str) -> Result<(), Error> {
    if id.is_empty() || id.len() > MAX_ID_BYTES {
        return Err(Error::InvalidArgument(format!(
            "session_id: expected 1 to {MAX_ID_BYTES} bytes, got {}",
            id.len()
        )));
    }
    Ok(())
}

/// The id a new session is stored under: a fresh UUID when `requested` is empty, else
/// `requested`, checked.
pub fn assign_id(requested: &str) -> Result<String, Error> {
    if requested.is_empty() {
        return Ok(uuid::Uuid::new_v4().to_string());
    }
    check_id(requested)?;
    Ok(requested.to_owned())
}

/// What `lookup` finds under `id` once the id is checked; NOT_FOUND when it finds nothing.
pub fn find<T>(id: &str, lookup: impl FnOnce(&str) -> Option<T>) -> Result<T, Error> {
    check_id(id)?;
    lookup(id).ok_or_else(|| Error::NotFound(id.to_owned()))
}
