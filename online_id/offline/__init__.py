"""Offline work on recordings shared by the commands, the archive and the evaluations (no argument parsing)."""
