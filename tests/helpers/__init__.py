"""Shared test helpers: fixtures data, virtual peers, isolated subprocesses, browsers."""
