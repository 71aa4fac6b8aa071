"""Evaluations that judge the diagnosis from outside: randomised worlds, written as users' files, the CLI run
as a user runs it, and the answers scored against the truth (no import of the diagnosis)."""
