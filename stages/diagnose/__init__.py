"""The Diagnose stage."""
