//! Decoding requests with bounded memory.
//!
//! prost decodes a repeated field by appending one element per occurrence, and an element can cost
//! far more decoded than on the wire: a one-byte session id is 3 bytes of protobuf but a 24-byte
//! `String` plus its allocation, and a step of 0 is one byte but a `u64`. A request of legal size
//! could therefore decode to twenty times its size before the handler rejects its length. So the
//! repeated fields of a batch are counted on the wire first, without allocating, and a message
//! that holds more than a legal batch is refused before prost sees it.
//!
//! [`BoundedCodec`] is the codec of the generated gRPC service (`build.rs` names it), and
//! [`decode`] is what message transports such as Zenoh call: both check the same
//! [`WireLimits`], and both report undecodable bytes as INVALID_ARGUMENT (the client's fault), not
//! the INTERNAL that tonic's prost codec answers.

use std::marker::PhantomData;

use bytes::Buf;
use prost::Message;
use tonic::codec::{Codec, DecodeBuf, Decoder};
use tonic::Status;
use tonic_prost::ProstEncoder;

use crate::error::{status, Error};
use crate::pb;

/// The batch limits are esa-core's, which checks them; the wire decoder bounds repeated fields
/// by them too.
pub use esa_core::batch::{MAX_BATCH_ITEMS, MAX_BATCH_VALUES};

/// Longest accepted session id, in bytes (esa-store's id rule).
pub use esa_store::MAX_ID_BYTES;

/// The encoded size of the largest legal request: a StepStream `step_linear_batch` whose probe is
/// the largest ProbeBatch ([`MAX_BATCH_ITEMS`] items with ids of [`MAX_ID_BYTES`] bytes, steps of
/// 10 varint bytes (the longest), [`MAX_BATCH_VALUES`] actions and as many action scales), with a
/// critic gain per action value, an offset per item and the paired flag (a `step_batch`, with
/// two values per item in place of the critic, is smaller). The server's default request size
/// limit.
pub const MAX_REQUEST_BYTES: usize = {
    // Field key plus the longest length prefix of a packed field (or of a message field).
    const FIELD: usize = 1 + 5;
    let id = 1 + 2 + MAX_ID_BYTES;
    let per_item = id + 10 + 1;
    let probe_batch = MAX_BATCH_ITEMS * per_item + 4 * FIELD + 2 * MAX_BATCH_VALUES * 8;
    let critic = 2 * FIELD + (MAX_BATCH_VALUES + MAX_BATCH_ITEMS) * 8 + 2;
    FIELD + FIELD + probe_batch + critic
};

/// Bounds on what a message's wire bytes may decode to, checked before decoding them.
pub trait WireLimits {
    /// Fails with INVALID_ARGUMENT when `bytes` hold more repeated elements than a legal message.
    fn check_wire(_bytes: &[u8]) -> Result<(), Error> {
        Ok(())
    }
}

/// Decodes `bytes` as a `M` after checking its [`WireLimits`].
pub fn decode<M: Message + Default + WireLimits>(mut bytes: impl Buf) -> Result<M, Error> {
    // Every caller passes one contiguous buffer (a gRPC message buffer or a Zenoh payload), so
    // the first chunk is the whole message.
    M::check_wire(bytes.chunk())?;
    M::decode(&mut bytes).map_err(|err| {
        Error::InvalidArgument(format!(
            "request: expected an encoded {} message: {err}",
            short_name::<M>()
        ))
    })
}

fn short_name<M>() -> &'static str {
    let name = std::any::type_name::<M>();
    name.rsplit("::").next().unwrap_or(name)
}

/// tonic's prost codec with [`decode`] on the receiving side.
pub struct BoundedCodec<T, U>(PhantomData<fn() -> (T, U)>);

impl<T, U> Default for BoundedCodec<T, U> {
    fn default() -> Self {
        Self(PhantomData)
    }
}

impl<T, U> Codec for BoundedCodec<T, U>
where
    T: Message + Send + 'static,
    U: Message + Default + WireLimits + Send + 'static,
{
    type Encode = T;
    type Decode = U;
    type Encoder = ProstEncoder<T>;
    type Decoder = BoundedDecoder<U>;

    fn encoder(&mut self) -> Self::Encoder {
        ProstEncoder::default()
    }

    fn decoder(&mut self) -> Self::Decoder {
        BoundedDecoder(PhantomData)
    }
}

/// The decoding half of [`BoundedCodec`].
pub struct BoundedDecoder<U>(PhantomData<fn() -> U>);

impl<U: Message + Default + WireLimits> Decoder for BoundedDecoder<U> {
    type Item = U;
    type Error = Status;

    fn decode(&mut self, buf: &mut DecodeBuf<'_>) -> Result<Option<U>, Status> {
        decode(buf).map(Some).map_err(status)
    }
}

/// How the elements of a repeated field are encoded.
#[derive(Clone, Copy)]
enum Elements {
    /// One length-delimited element per occurrence (strings).
    Strings,
    /// Varints: one per occurrence, or packed (one per byte below 0x80).
    Varints,
    /// 8-byte values: one per occurrence, or packed (eight bytes each).
    Fixed64,
}

/// What the counting pass knows about one field number.
#[derive(Clone, Copy)]
enum Rule {
    Repeated {
        name: &'static str,
        elements: Elements,
        max: usize,
    },
    /// A message field: its fields are counted with the same counters, so occurrences that prost
    /// would merge into one message add up.
    Message(&'static [(u32, Rule)]),
}

const fn repeated(name: &'static str, elements: Elements, max: usize) -> Rule {
    Rule::Repeated {
        name,
        elements,
        max,
    }
}

const PROBE_BATCH: &[(u32, Rule)] = &[
    (
        1,
        repeated("session_ids", Elements::Strings, MAX_BATCH_ITEMS),
    ),
    (2, repeated("steps", Elements::Varints, MAX_BATCH_ITEMS)),
    (3, repeated("actions", Elements::Fixed64, MAX_BATCH_VALUES)),
    (
        4,
        repeated("episode_starts", Elements::Varints, MAX_BATCH_ITEMS),
    ),
    (
        5,
        repeated("action_scales", Elements::Fixed64, MAX_BATCH_VALUES),
    ),
];

const REPORT_BATCH: &[(u32, Rule)] = &[
    (
        1,
        repeated("session_ids", Elements::Strings, MAX_BATCH_ITEMS),
    ),
    (2, repeated("steps", Elements::Varints, MAX_BATCH_ITEMS)),
    (3, repeated("q_values", Elements::Fixed64, MAX_BATCH_ITEMS)),
    (
        4,
        repeated("q_references", Elements::Fixed64, MAX_BATCH_ITEMS),
    ),
];

// The critic's fields are numbered after the probe batch's, so each field has its own counter.
const STEP_LINEAR_BATCH: &[(u32, Rule)] = &[
    (1, Rule::Message(PROBE_BATCH)),
    (
        6,
        repeated("critic_gains", Elements::Fixed64, MAX_BATCH_VALUES),
    ),
    (
        7,
        repeated("critic_offsets", Elements::Fixed64, MAX_BATCH_ITEMS),
    ),
];

// The critic's values are numbered after the probe batch's fields too.
const STEP_BATCH: &[(u32, Rule)] = &[
    (1, Rule::Message(PROBE_BATCH)),
    (6, repeated("q_values", Elements::Fixed64, MAX_BATCH_ITEMS)),
    (
        7,
        repeated("q_references", Elements::Fixed64, MAX_BATCH_ITEMS),
    ),
];

// A legal StepStream message holds one batch, so the kinds may share counters: a message
// holding several only ever counts more, never less.
const STEP_STREAM: &[(u32, Rule)] = &[
    (1, Rule::Message(PROBE_BATCH)),
    (2, Rule::Message(REPORT_BATCH)),
    (3, Rule::Message(STEP_LINEAR_BATCH)),
    (4, Rule::Message(STEP_BATCH)),
];

/// Element counters, indexed by field number (the batch messages number theirs 1 to 7).
type Counts = [usize; 8];

fn check_fields(bytes: &[u8], rules: &[(u32, Rule)]) -> Result<(), Error> {
    let mut counts = Counts::default();
    let mut over = None;
    count_fields(bytes, rules, &mut counts, &mut over).map_err(|what| {
        Error::InvalidArgument(format!("request: expected an encoded message: {what}"))
    })?;
    match over {
        None => Ok(()),
        Some(Over { name, max, number }) => {
            let got = counts.get(number).copied().unwrap_or_default();
            Err(Error::InvalidArgument(format!(
                "{name}: expected at most {max} per batch, got {got}"
            )))
        }
    }
}

/// The first field found over its limit; counting goes on to the end of the message, so
/// that the error can say how many there were.
struct Over {
    name: &'static str,
    max: usize,
    number: usize,
}

fn count_fields(
    mut bytes: &[u8],
    rules: &[(u32, Rule)],
    counts: &mut Counts,
    over: &mut Option<Over>,
) -> Result<(), &'static str> {
    while !bytes.is_empty() {
        let key = varint(&mut bytes)?;
        let number = key >> 3;
        let rule = rules
            .iter()
            .find(|(n, _)| u64::from(*n) == number)
            .map(|&(n, rule)| (n as usize, rule));
        let elements = match key & 7 {
            0 => {
                varint(&mut bytes)?;
                1
            }
            1 => {
                take(&mut bytes, 8)?;
                1
            }
            2 => {
                let len =
                    usize::try_from(varint(&mut bytes)?).map_err(|_| "length out of range")?;
                let payload = take(&mut bytes, len)?;
                match rule {
                    Some((_, Rule::Message(inner))) => {
                        count_fields(payload, inner, counts, over)?;
                        continue;
                    }
                    Some((_, Rule::Repeated { elements, .. })) => match elements {
                        Elements::Strings => 1,
                        Elements::Varints => payload.iter().filter(|&&b| b < 0x80).count(),
                        Elements::Fixed64 => payload.len() / 8,
                    },
                    None => 0,
                }
            }
            5 => {
                take(&mut bytes, 4)?;
                1
            }
            // Groups (3, 4) are not proto3; anything else is not protobuf.
            _ => return Err("unsupported wire type"),
        };
        if let Some((number, Rule::Repeated { name, max, .. })) = rule {
            if let Some(count) = counts.get_mut(number) {
                *count += elements;
                if *count > max && over.is_none() {
                    *over = Some(Over { name, max, number });
                }
            }
        }
    }
    Ok(())
}

fn varint(bytes: &mut &[u8]) -> Result<u64, &'static str> {
    let mut value = 0u64;
    for shift in (0..70).step_by(7) {
        let (&byte, rest) = bytes.split_first().ok_or("truncated varint")?;
        *bytes = rest;
        value |= u64::from(byte & 0x7f).checked_shl(shift).unwrap_or(0);
        if byte < 0x80 {
            return Ok(value);
        }
    }
    Err("varint longer than 10 bytes")
}

fn take<'a>(bytes: &mut &'a [u8], len: usize) -> Result<&'a [u8], &'static str> {
    let (head, tail) = bytes
        .split_at_checked(len)
        .ok_or("field runs past the end of the message")?;
    *bytes = tail;
    Ok(head)
}

impl WireLimits for pb::ProbeBatchRequest {
    fn check_wire(bytes: &[u8]) -> Result<(), Error> {
        check_fields(bytes, PROBE_BATCH)
    }
}

impl WireLimits for pb::ReportBatchRequest {
    fn check_wire(bytes: &[u8]) -> Result<(), Error> {
        check_fields(bytes, REPORT_BATCH)
    }
}

impl WireLimits for pb::StepStreamRequest {
    fn check_wire(bytes: &[u8]) -> Result<(), Error> {
        check_fields(bytes, STEP_STREAM)
    }
}

/// Requests without repeated strings or varints decode to about their wire size. (Only requests
/// are decoded here: the server's generated code is the only user of [`BoundedCodec`].)
macro_rules! no_wire_limits {
    ($($message:ty),* $(,)?) => { $(impl WireLimits for $message {})* };
}

no_wire_limits!(
    pb::CreateSessionRequest,
    pb::ProbeRequest,
    pb::ReportRequest,
    pb::EndEpisodeRequest,
    pb::CloseSessionRequest,
    pb::GetSessionRequest,
);

#[cfg(test)]
mod tests {
    use super::*;

    fn probe_batch(n: usize, d: usize) -> pb::ProbeBatchRequest {
        pb::ProbeBatchRequest {
            session_ids: (0..n).map(|i| format!("{i:0>128}")).collect(),
            steps: vec![u64::MAX; n],
            actions: vec![0.5; n * d],
            episode_starts: vec![true; n],
            action_scales: vec![1.0; n * d],
        }
    }

    #[test]
    fn the_largest_legal_request_fits_the_default_limit_exactly() {
        let batch = probe_batch(MAX_BATCH_ITEMS, MAX_BATCH_VALUES / MAX_BATCH_ITEMS);
        let step = pb::StepLinearBatchRequest {
            probe: Some(batch),
            critic_gains: vec![0.5; MAX_BATCH_VALUES],
            critic_offsets: vec![0.5; MAX_BATCH_ITEMS],
            paired: true,
        };
        let message = pb::StepStreamRequest {
            kind: Some(pb::step_stream_request::Kind::StepLinearBatch(step)),
        };
        let bytes = message.encode_to_vec();
        assert!(bytes.len() <= MAX_REQUEST_BYTES, "{}", bytes.len());
        assert!(bytes.len() + 64 > MAX_REQUEST_BYTES, "{}", bytes.len());
        assert!(decode::<pb::StepStreamRequest>(bytes.as_slice()).is_ok());
    }

    #[test]
    fn one_id_too_many_is_refused_before_decoding() {
        let mut batch = probe_batch(MAX_BATCH_ITEMS, 0);
        assert!(decode::<pb::ProbeBatchRequest>(batch.encode_to_vec().as_slice()).is_ok());
        batch.session_ids.push(String::new());
        let err = decode::<pb::ProbeBatchRequest>(batch.encode_to_vec().as_slice()).unwrap_err();
        assert_eq!(err.code(), crate::error::Code::InvalidArgument);
        assert!(err.to_string().contains("session_ids"), "{err}");
        assert!(err.to_string().contains("65537"), "{err}");
    }

    #[test]
    fn packed_and_unpacked_varints_both_count() {
        let mut packed = Vec::new();
        prost::encoding::uint64::encode_packed(2, &vec![0; MAX_BATCH_ITEMS + 1], &mut packed);
        let mut unpacked = Vec::new();
        prost::encoding::uint64::encode_repeated(2, &vec![0; MAX_BATCH_ITEMS + 1], &mut unpacked);
        for bytes in [packed, unpacked] {
            let err = decode::<pb::ReportBatchRequest>(bytes.as_slice()).unwrap_err();
            assert!(err.to_string().contains("steps"), "{err}");
        }
    }

    #[test]
    fn stream_messages_that_prost_would_merge_add_up() {
        let half = pb::StepStreamRequest {
            kind: Some(pb::step_stream_request::Kind::ReportBatch(
                pb::ReportBatchRequest {
                    session_ids: vec![String::new(); MAX_BATCH_ITEMS / 2 + 1],
                    ..Default::default()
                },
            )),
        };
        let once = half.encode_to_vec();
        assert!(decode::<pb::StepStreamRequest>(once.as_slice()).is_ok());
        let twice = [once.as_slice(), once.as_slice()].concat();
        assert!(decode::<pb::StepStreamRequest>(twice.as_slice()).is_err());
    }

    #[test]
    fn critic_values_past_the_limit_are_refused_before_decoding() {
        let step = |gains: usize| pb::StepStreamRequest {
            kind: Some(pb::step_stream_request::Kind::StepLinearBatch(
                pb::StepLinearBatchRequest {
                    probe: Some(probe_batch(MAX_BATCH_ITEMS, 1)),
                    critic_gains: vec![0.0; gains],
                    critic_offsets: vec![0.0; MAX_BATCH_ITEMS],
                    paired: false,
                },
            )),
        };
        let legal = step(MAX_BATCH_VALUES).encode_to_vec();
        assert!(decode::<pb::StepStreamRequest>(legal.as_slice()).is_ok());
        let over = step(MAX_BATCH_VALUES + 1).encode_to_vec();
        let err = decode::<pb::StepStreamRequest>(over.as_slice()).unwrap_err();
        assert!(err.to_string().contains("critic_gains"), "{err}");
    }

    #[test]
    fn given_values_past_the_limit_are_refused_before_decoding() {
        let step = |values: usize, references: usize| pb::StepStreamRequest {
            kind: Some(pb::step_stream_request::Kind::StepBatch(
                pb::StepBatchRequest {
                    probe: Some(probe_batch(MAX_BATCH_ITEMS, 1)),
                    q_values: vec![0.0; values],
                    q_references: vec![0.0; references],
                },
            )),
        };
        let legal = step(MAX_BATCH_ITEMS, MAX_BATCH_ITEMS).encode_to_vec();
        assert!(legal.len() < MAX_REQUEST_BYTES, "{}", legal.len());
        assert!(decode::<pb::StepStreamRequest>(legal.as_slice()).is_ok());
        for (values, references, name) in [
            (MAX_BATCH_ITEMS + 1, 0, "q_values"),
            (0, MAX_BATCH_ITEMS + 1, "q_references"),
        ] {
            let over = step(values, references).encode_to_vec();
            let err = decode::<pb::StepStreamRequest>(over.as_slice()).unwrap_err();
            assert!(err.to_string().contains(name), "{err}");
        }
    }

    #[test]
    fn garbage_is_invalid_argument_naming_the_message() {
        for bytes in [&b"\xff\xff\xff"[..], b"\x0a\x05ab", b"\x0b"] {
            let err = decode::<pb::ProbeBatchRequest>(bytes).unwrap_err();
            assert_eq!(err.code(), crate::error::Code::InvalidArgument, "{err}");
        }
        let err = decode::<pb::ProbeRequest>(&b"\xff\xff\xff"[..]).unwrap_err();
        assert!(err.to_string().contains("ProbeRequest"), "{err}");
    }
}
