"""Extensions that ship with fleetgcs (list them in ``[daemon] extensions``; see docs/api.md)."""
