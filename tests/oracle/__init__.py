"""Test-only reference implementations the frame engine is checked against."""
