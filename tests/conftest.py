"""Test configuration: every test is seeded (hypothesis runs derandomized)."""

from hypothesis import HealthCheck, settings

settings.register_profile(
    "tumblenav",
    derandomize=True,
    deadline=None,
    max_examples=60,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.load_profile("tumblenav")
