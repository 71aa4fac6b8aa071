"""Adapters: the only modules that touch files, python-can or cantools."""
