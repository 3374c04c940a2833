"""The fusion processor: its options, and its loop ticking the tracker without input."""

from __future__ import annotations

import subprocess
import sys
from datetime import UTC, datetime, timedelta
from pathlib import Path

import anyio
import pytest
from pydantic import ValidationError

from gateway.events import Detection, Event, Position, Sensor, Track
from processors.fusion import FusionConfig, FusionProcessor
from tracking import TrackerSettings

T0 = datetime(2026, 3, 1, 12, 0, tzinfo=UTC)


class TestFusionConfig:
    """Options validated at load, every error naming its option."""

    def test_defaults_match_the_tracker(self) -> None:
        settings, default = FusionConfig().settings(), TrackerSettings()
        for name in ("gate_sigma", "max_gap_s", "coast_after_s", "lost_after_s", "confirm_hits",
                     "confirm_window", "max_tracks", "update_interval_s", "merge_sigma",
                     "merge_after", "report_velocity_sigma_mps", "index", "cell_m"):  # fmt: skip
            assert getattr(settings, name) == getattr(default, name), name
        for name in default.priors.names():
            assert settings.priors[name] == default.priors[name], name

    def test_class_priors_and_the_speed_floor_reach_the_tracker(self) -> None:
        config = FusionConfig.model_validate(
            {"class_priors": {"tank": {"max_speed_mps": 15, "accel_mps2": 0.5}},
             "max_speed_mps": 18}
        )  # fmt: skip
        priors = config.settings().priors
        assert priors["tank"].max_speed_mps == 18.0  # raised to the floor
        assert priors["tank"].accel_mps2 == 0.5
        assert priors["uav"].max_speed_mps == TrackerSettings().priors["uav"].max_speed_mps

    @pytest.mark.parametrize(
        ("options", "where"),
        [
            ({"gate_sigma": 0}, "gate_sigma"),
            ({"max_tracks": 0}, "max_tracks"),
            ({"index": "kdtree"}, "index"),
            ({"classes": ["tank", "tank"]}, "classes"),
            ({"classes": ["tank", "other"]}, "classes"),
            ({"gate_sigm": 3}, "gate_sigm"),
            ({"confirm_hits": 6, "confirm_window": 5}, "confirm_hits"),
            ({"class_priors": {"tank": {"max_speed_mps": -1, "accel_mps2": 1}}}, "max_speed_mps"),
        ],
    )
    def test_a_bad_option_is_named(self, options: dict[str, object], where: str) -> None:
        with pytest.raises(ValidationError) as caught:
            FusionConfig.model_validate(options)
        assert where in str(caught.value)

    def test_hostile_classes_must_be_in_the_frame(self) -> None:
        with pytest.raises(ValidationError, match="hostile_classes"):
            FusionConfig(classes=("uav",), hostile_classes=("tank",))

    def test_check_config_names_the_option_and_line(self, tmp_path: Path) -> None:
        config = tmp_path / "c.yaml"
        config.write_text(
            "airframes:\n  - {id: A, sysid: 1, links: [{uri: 'udp://127.0.0.1:14550', "
            "security: unsecured}]}\n"
            "processors:\n  - {name: fusion, type: fusion, options: {gate_sigma: -1}}\n"
        )
        result = subprocess.run(
            [sys.executable, "-m", "gateway", "check-config", str(config)],
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
        )
        assert result.returncode == 2
        assert "processors[0].options.gate_sigma" in result.stderr


@pytest.mark.anyio
async def test_run_ages_tracks_without_input() -> None:
    """A confirmed track, then silence: the tick alone reports it lost."""
    processor = FusionProcessor(
        "fusion",
        FusionConfig(lost_after_s=5.0, tick_s=0.01),
        clock=lambda: T0 + timedelta(seconds=10),
    )
    published: list[Track] = []
    lost = anyio.Event()

    def publish(event: Event) -> None:
        assert isinstance(event, Track)
        published.append(event)
        if event.status == "lost":
            lost.set()

    send, receive = anyio.create_memory_object_stream[Event](10)
    with anyio.fail_after(5):
        async with anyio.create_task_group() as tg:
            await tg.start(processor.run, receive, publish)
            for n in range(3):  # three detections confirm it (M of N)
                await send.send(
                    Detection(
                        event_id=f"d{n}",
                        airframe="A",
                        time=T0 + timedelta(seconds=n),
                        sensor=Sensor.EO,
                        object_class="uav",
                        confidence=0.7,
                        position=Position(lat_deg=65.8, lon_deg=21.7),
                        sigma_h_m=5.0,
                    )
                )
            await lost.wait()
            send.close()
    assert [t.status for t in published] == ["created", "lost"]
    assert processor.status()["lost"] == 1
