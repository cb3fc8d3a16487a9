"""Missions: the runner, synchronization barriers, the release journal, imported mission files."""
