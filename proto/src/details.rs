//! Which item of a batch an error is about, as data rather than text.
//!
//! A failed `ProbeBatch` or `ReportBatch` item names its position in the
//! request, [`v1::BatchItem`]. Each transport carries it beside the error's
//! code and message:
//!
//! - unary gRPC: the status details, i.e. the `grpc-status-details-bin`
//!   trailer holding an encoded `google.rpc.Status` ([`RpcStatus`]) whose
//!   `details` hold one `google.protobuf.Any` of type [`BATCH_ITEM_TYPE_URL`]
//!   (the standard rich error model, readable with grpcio-status, tonic-types
//!   or any gRPC library's status-details helper);
//! - StepStream and Zenoh: the `item` field of the `StreamError`.

use bytes::Bytes;
use prost::Message;
use prost_types::Any;

use crate::v1;

/// The `Any` type URL of a [`v1::BatchItem`] in a status's details.
pub const BATCH_ITEM_TYPE_URL: &str = "type.googleapis.com/esa.v1.BatchItem";

/// `google.rpc.Status` (`google/rpc/status.proto`): what the
/// `grpc-status-details-bin` trailer of a gRPC status holds.
#[derive(Clone, PartialEq, Message)]
pub struct RpcStatus {
    /// The gRPC status code number.
    #[prost(int32, tag = "1")]
    pub code: i32,
    /// The status message.
    #[prost(string, tag = "2")]
    pub message: String,
    /// Structured details, each an `Any`.
    #[prost(message, repeated, tag = "3")]
    pub details: Vec<Any>,
}

/// The status details of an error about batch item `index`: the bytes of the
/// `grpc-status-details-bin` trailer (tonic's `Status::with_details`).
pub fn status_details(code: i32, message: &str, index: u32) -> Bytes {
    let item = Any {
        type_url: BATCH_ITEM_TYPE_URL.to_string(),
        value: v1::BatchItem { index }.encode_to_vec(),
    };
    let status = RpcStatus {
        code,
        message: message.to_string(),
        details: vec![item],
    };
    Bytes::from(status.encode_to_vec())
}

/// The batch item that the status details `details` name, if they name one.
pub fn batch_item(details: &[u8]) -> Option<u32> {
    let status = RpcStatus::decode(details).ok()?;
    status
        .details
        .iter()
        .find(|any| any.type_url == BATCH_ITEM_TYPE_URL)
        .and_then(|any| v1::BatchItem::decode(any.value.as_slice()).ok())
        .map(|item| item.index)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_item_round_trips_through_the_status_details() {
        let details = status_details(3, "item 4: bad", 4);
        assert_eq!(batch_item(&details), Some(4));
        let status = RpcStatus::decode(details.as_ref()).unwrap();
        assert_eq!((status.code, status.message.as_str()), (3, "item 4: bad"));
        assert_eq!(batch_item(b""), None);
        assert_eq!(batch_item(b"\xff"), None);
    }
}
