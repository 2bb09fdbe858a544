"""A task repeated on the map of the first, as a deployment keeps its map between tasks: the
second goes straight to what the first found (ovamos.bench.episode's world, the services' cores)."""

from __future__ import annotations

from ovamos.bench.episode import EpisodeConfig, EpisodeWorld, episode_config, run_task
from ovamos.world.episodes import make_episode
from ovamos.world.perception_presets import perception_preset

# Development seed 1, episode 18 (three targets, found by the first task): taking the confirmed
# objects in the order the map confirmed them, the second task's first STOP came at step 69.
SEED, EPISODE = 1, 18


def test_a_repeated_task_stops_at_a_target_right_after_its_first_look_around() -> None:
    spec, scene, truth = make_episode(SEED, EPISODE)
    config = episode_config("ovamos", EpisodeConfig(perception=perception_preset("realistic")))
    world = EpisodeWorld(scene, truth, config, spec.start)
    try:
        first = run_task(world, spec)
        assert first.success, first.stops
        again = spec.model_copy(update={"episode_id": f"{spec.episode_id}-again", "start": world.robot.pose})
        second = run_task(world, again)
    finally:
        world.close()
    assert second.success, second.stops
    assert all(stop.success for stop in second.stops)
    # the look around every task starts with, then the nearest target, where the first task found it
    assert second.stops[0].step == config.agent.initial_turns + 1
    assert second.steps < first.steps / 2
    assert second.path_m < first.path_m and second.trajectory[0] == first.trajectory[-1]
