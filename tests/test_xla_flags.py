"""jdem turns off XLA:CPU's YNNPACK fusions on jaxlib 0.10 unless told not to
(jdem/__init__.py; the speed-up is measured by experiments/benchmark.py)."""
import os
from importlib import metadata

import pytest

import jdem

FLAG = "--xla_cpu_experimental_ynn_fusion_type="
JAXLIB_010 = metadata.version("jaxlib").startswith("0.10.")


@pytest.fixture
def env(monkeypatch):
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    monkeypatch.delenv("JDEM_KEEP_XLA_FLAGS", raising=False)
    return monkeypatch


@pytest.mark.skipif(not JAXLIB_010, reason="the flag is only set on jaxlib 0.10")
def test_flag_added_and_other_flags_kept(env):
    jdem._cpu_fusion_flag()
    assert os.environ["XLA_FLAGS"] == FLAG
    env.setenv("XLA_FLAGS", "--xla_force_host_platform_device_count=4")
    jdem._cpu_fusion_flag()
    assert os.environ["XLA_FLAGS"] == "--xla_force_host_platform_device_count=4 " + FLAG


def test_user_choice_is_left_alone(env):
    env.setenv("XLA_FLAGS", "--xla_cpu_experimental_ynn_fusion_type=reduce")
    jdem._cpu_fusion_flag()
    assert os.environ["XLA_FLAGS"] == "--xla_cpu_experimental_ynn_fusion_type=reduce"
    env.setenv("XLA_FLAGS", "--xla_force_host_platform_device_count=2")
    env.setenv("JDEM_KEEP_XLA_FLAGS", "1")
    jdem._cpu_fusion_flag()
    assert os.environ["XLA_FLAGS"] == "--xla_force_host_platform_device_count=2"
