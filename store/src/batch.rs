//! How a batch finds its sessions: by id, in item order, each at most once.

use crate::{find, Error};

/// The sessions of a batch as `lookup` found them, in item order.
#[derive(Debug)]
pub struct Resolved<T> {
    /// What `lookup` returned for each item, in item order.
    pub items: Vec<T>,
    /// The item indices sorted by their key (stable): an order in which a concurrent store can
    /// lock the sessions, the same for every batch, so two batches cannot deadlock.
    pub order: Vec<usize>,
}

/// Finds the sessions of `ids`, in item order: each id well formed ([`crate::check_id`]) and
/// found by `lookup` (NOT_FOUND otherwise), every item's id checked and looked up before any
/// repeat is looked for; then each session (told apart by `key`) at most once. An error names
/// the failing item: the first that failed its lookup, else the first repeat, which names the
/// item it repeats.
pub fn resolve_batch<S, T, K>(
    ids: &[S],
    mut lookup: impl FnMut(&str) -> Option<T>,
    key: impl Fn(&T) -> K,
) -> Result<Resolved<T>, Error>
where
    S: AsRef<str>,
    K: Ord,
{
    let items = ids
        .iter()
        .enumerate()
        .map(|(index, id)| find(id.as_ref(), &mut lookup).map_err(|err| Error::item(index, err)))
        .collect::<Result<Vec<_>, _>>()?;
    let mut order: Vec<usize> = (0..items.len()).collect();
    // Stable: the repeats of one session stay in item order, side by side.
    order.sort_by_key(|&index| items.get(index).map(&key));
    let repeat = order
        .windows(2)
        .filter_map(|pair| match *pair {
            [first, second] => {
                let same = items.get(first).map(&key) == items.get(second).map(&key);
                same.then_some((second, first))
            }
            _ => None,
        })
        .min();
    if let Some((index, first)) = repeat {
        let id = ids.get(index).map_or("", AsRef::as_ref);
        return Err(Error::item(index, Error::repeated(id, first)));
    }
    Ok(Resolved { items, order })
}
