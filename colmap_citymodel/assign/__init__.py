"""Tie points -> model planes: direct assignment and the indirect (MSAC) methods behind one
interface."""
