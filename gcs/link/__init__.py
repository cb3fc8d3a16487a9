"""The agent link: admission, sessions, the status table, outboxes, hook dispatch, the release beacon."""
