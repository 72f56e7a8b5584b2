//! Every message and code of the store's errors, tested here once for both wrappers (the server
//! and the in-process engine report them unchanged).

use esa_core::batch::BatchError;
use esa_core::{CoreError, Session, SessionConfig};
use esa_store::{
    assign_id, check_id, resolve_batch, Code, Error, Key, Sessions, DEFAULT_MAX_SESSIONS,
    MAX_ID_BYTES,
};

fn session(learning_rate: f64) -> Session {
    let config = SessionConfig::new(1, 0.01, vec![0.2], vec![60.0], vec![learning_rate]);
    Session::new(config).expect("a valid config")
}

fn store(ids: &[&str]) -> Sessions {
    let mut sessions = Sessions::new(DEFAULT_MAX_SESSIONS);
    for id in ids {
        sessions.create(id, session(0.25)).expect("created");
    }
    sessions
}

fn refused(err: &Error, code: Code, index: Option<usize>, message: &str) {
    assert_eq!((err.code(), err.item_index()), (code, index), "{err}");
    assert_eq!(err.to_string(), message);
}

#[test]
fn ids_are_1_to_128_bytes_and_an_empty_one_asks_for_a_uuid() {
    assert_eq!(MAX_ID_BYTES, 128);
    check_id(&"x".repeat(128)).expect("128 bytes");
    for (id, len) in [("", 0), (&*"x".repeat(129), 129)] {
        let err = check_id(id).unwrap_err();
        let message = format!("session_id: expected 1 to 128 bytes, got {len}");
        refused(&err, Code::InvalidArgument, None, &message);
    }
    let fresh = assign_id("").expect("a uuid");
    assert_eq!((fresh.len(), fresh.matches('-').count()), (36, 4));
    assert_eq!(assign_id("mine").as_deref(), Ok("mine"));
    let long = assign_id(&"x".repeat(129)).unwrap_err();
    assert_eq!(long.code(), Code::InvalidArgument);
}

#[test]
fn an_unknown_or_closed_session_is_not_found() {
    let mut sessions = store(&["a"]);
    sessions.close("a").expect("closed");
    let message = "session \"a\" not found: it is unknown, was closed or expired after being \
                   idle; create it with CreateSession";
    refused(
        &sessions.close("a").unwrap_err(),
        Code::NotFound,
        None,
        message,
    );
    refused(
        &sessions.get_mut("a").unwrap_err(),
        Code::NotFound,
        None,
        message,
    );
    refused(
        &sessions.key("a").unwrap_err(),
        Code::NotFound,
        None,
        message,
    );
    let err = sessions.get_mut("").unwrap_err();
    assert_eq!(err.code(), Code::InvalidArgument);
}

#[test]
fn creating_an_existing_id_keeps_it_for_the_same_config_only() {
    let mut sessions = store(&["a"]);
    assert_eq!(sessions.create("a", session(0.25)).as_deref(), Ok("a"));
    let err = sessions.create("a", session(0.5)).unwrap_err();
    let message = "session \"a\" already exists with a different config; close it first, or \
                   create it with another id";
    refused(&err, Code::AlreadyExists, None, message);
    assert_eq!(sessions.live(), 1);
}

#[test]
fn the_session_limit_is_resource_exhausted_but_an_existing_id_still_answers() {
    assert_eq!(DEFAULT_MAX_SESSIONS, 100_000);
    let mut sessions = Sessions::new(2);
    sessions.create("a", session(0.25)).expect("a");
    sessions.create("b", session(0.25)).expect("b");
    let err = sessions.create("c", session(0.25)).unwrap_err();
    let message = "session limit reached: 2 live sessions, at most 2 (esa-server \
                   --max-sessions, Engine max_sessions); close finished sessions or raise the \
                   limit";
    refused(&err, Code::ResourceExhausted, None, message);
    assert_eq!(sessions.create("a", session(0.25)).as_deref(), Ok("a"));
    sessions.close("a").expect("closed");
    sessions.create("c", session(0.25)).expect("room again");
}

#[test]
fn a_batch_finds_its_sessions_by_id_in_item_order() {
    let sessions = store(&["b", "a", "c"]);
    let keys = sessions.resolve(&["c", "a", "b"]).expect("resolved");
    let expected: Vec<Key> = ["c", "a", "b"]
        .iter()
        .map(|id| sessions.key(id).expect("live"))
        .collect();
    assert_eq!(keys, expected);
}

#[test]
fn a_batch_names_the_item_that_failed_lookups_before_repeats() {
    let sessions = store(&["a", "b"]);
    let not_found = "item 2: session \"ghost\" not found: it is unknown, was closed or expired \
                     after being idle; create it with CreateSession";
    let err = sessions.resolve(&["a", "a", "ghost"]).unwrap_err();
    refused(&err, Code::NotFound, Some(2), not_found);
    let err = sessions.resolve(&["a", "", "b"]).unwrap_err();
    let bad_id = "item 1: session_id: expected 1 to 128 bytes, got 0";
    refused(&err, Code::InvalidArgument, Some(1), bad_id);
}

#[test]
fn a_repeated_session_is_refused_at_its_first_repeat() {
    let sessions = store(&["a", "b"]);
    let err = sessions.resolve(&["a", "b", "b", "a"]).unwrap_err();
    let message = "item 2: session id \"b\" also appears at item 1; a session may appear at \
                   most once per batch";
    refused(&err, Code::InvalidArgument, Some(2), message);
    // By the key that tells sessions apart, whatever the order it sorts them in.
    let resolved = resolve_batch(&["x", "y", "z"], |id| Some(id.len()), |len| *len).unwrap_err();
    assert_eq!(resolved.item_index(), Some(1));
    let ok = resolve_batch(&["x", "yyy", "zz"], |id| Some(id.len()), |n| usize::MAX - n);
    assert_eq!(ok.expect("distinct").order, vec![1, 2, 0]);
}

#[test]
fn core_and_batch_errors_keep_their_words_and_get_their_codes() {
    let mismatch = Error::from(CoreError::StepMismatch {
        expected: 0,
        got: 1,
    });
    refused(
        &mismatch,
        Code::FailedPrecondition,
        None,
        "step mismatch: expected step 0, got 1",
    );
    let no_probe = Error::from(CoreError::NoPendingProbe { step: 3 });
    assert_eq!(no_probe.code(), Code::FailedPrecondition);
    let config = Error::from(CoreError::InvalidConfig("dt: expected > 0".into()));
    refused(
        &config,
        Code::InvalidArgument,
        None,
        "invalid config: dt: expected > 0",
    );
    let item = Error::from(BatchError::Item {
        index: 4,
        error: CoreError::InvalidArgument("action: NaN".into()),
    });
    refused(
        &item,
        Code::InvalidArgument,
        Some(4),
        "item 4: invalid argument: action: NaN",
    );
    let request = Error::from(BatchError::Request(
        "steps: expected 2 values, got 1".into(),
    ));
    refused(
        &request,
        Code::InvalidArgument,
        None,
        "steps: expected 2 values, got 1",
    );
    for (code, number) in [
        (Code::InvalidArgument, 3),
        (Code::DeadlineExceeded, 4),
        (Code::NotFound, 5),
        (Code::AlreadyExists, 6),
        (Code::ResourceExhausted, 8),
        (Code::FailedPrecondition, 9),
        (Code::Unavailable, 14),
        (Code::Unauthenticated, 16),
    ] {
        assert_eq!(
            code as i32, number,
            "{code:?} is numbered as gRPC numbers it"
        );
    }
}

#[test]
fn a_key_cached_before_a_close_does_not_find_the_session_created_after_it() {
    let mut sessions = store(&["a"]);
    let old = sessions.key("a").expect("live");
    sessions.close("a").expect("closed");
    sessions.create("a", session(0.5)).expect("again");
    assert!(sessions.session(old).is_none() && sessions.take(old).is_none());
    let new = sessions.key("a").expect("live");
    assert_eq!(new.slot, old.slot, "the freed slot is reused");
    let mut taken = sessions.take(new).expect("taken");
    assert_eq!(taken.session().episodes_completed(), 0);
    assert!(sessions.take(new).is_none(), "taken already");
    sessions.put(taken);
    assert!(sessions.session(new).is_some());
}
