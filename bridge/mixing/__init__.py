"""Mixing: the autopilot's input vector in, one command fraction per ESC output out."""
