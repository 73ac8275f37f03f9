"""Fixtures of the integration tests (the shared ones are in tests/conftest.py)."""

from tests.integration.fuzz_support import live

__all__ = ["live"]
