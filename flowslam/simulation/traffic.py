"""Moving actors: vehicles, cyclists and pedestrians on the network's tracks, the ego's
convoy and an oncoming stream; a time-stepped traffic simulation and a final collision check.

Kinematics (time step ``DT``): every actor moves along its current track with the
Intelligent Driver Model (desired speed, comfortable acceleration/braking, time
headway, minimum gap) behind its leader on the same track (or the next tracks it
will take), never moving further than the gap to that leader. Desired speeds:
cars 8-15 m/s, trucks 7-12 m/s, cyclists 3-7 m/s (all capped in curves at 2.5 m/s^2
lateral acceleration); pedestrians 0.5-2 m/s.

- Vehicles pick a random connector at each intersection (never a U-turn, never into
  a lane of the ego route). Entering a connector (gated track) needs a grant: no
  conflicting connector in use, room on the exit lane, and the ego group (the ego
  and its convoy) not coming near the connector while the vehicle needs to clear it.
  Vehicles stop at the line otherwise, and before crosswalks in use.
- Walkers follow the sidewalk loops. Crossers shuttle over a crosswalk, starting only
  when no vehicle is on or close to it and the ego group will not reach it before they
  are across.
- Convoy vehicles move with the ego along its route at a fixed arc-length offset
  (e.g. a lead car 17 m ahead): they are dynamic in the world but static relative to
  the sensor, the classic trap for ego-motion from flow. An oncoming stream (procedural
  loops) drives the ego's loops the other way in the oncoming lanes, a fixed headway
  apart. Convoy and stream are scripted: everybody else yields to them (the lanes they
  use are closed to other vehicles; gates and crosswalks wait for them), and an
  oncoming vehicle that would touch the ego or the convoy is left out.
- A vehicle at a dead end (the end of the oncoming lane of a given path) waits there
  and leaves the scene once the ego is out of sensor range.

After the simulation every pair of actor footprints, and each actor against the
ego group and the static obstacles, is checked at every step; an actor that
overlaps anything is removed from the whole sequence (``ActorSet.removed`` counts
them), so actors never interpenetrate each other or the ego vehicle.

This module holds ``simulate_traffic``, which runs those stages in order; the stages
live in ``traffic_spec`` (``TrafficSpec``, ``DT``), ``traffic_scripted`` (convoy,
oncoming stream, the ego group), ``traffic_spawn``, ``traffic_stepping`` (IDM,
right of way) and ``traffic_validation`` (overlap checks), the result types in
``actors`` (``Actor``, ``ActorSet``). Poses are in the town frame (metres, radians),
times in seconds.
"""

from __future__ import annotations

import numpy as np

from flowslam.simulation import labels
from flowslam.simulation.actors import Actor, ActorSet
from flowslam.simulation.ego_path import EgoMotion
from flowslam.simulation.meshes import ActorShape, shapes_of_kind
from flowslam.simulation.roads import RoadNetwork
from flowslam.simulation.town import StaticWorld
from flowslam.simulation.traffic_scripted import EgoGroup, scripted_tracks
from flowslam.simulation.traffic_spawn import spawn_agents
from flowslam.simulation.traffic_spec import DT, TrafficSpec
from flowslam.simulation.traffic_stepping import agents_to_actors, prepare_speed_caps, run_steps
from flowslam.simulation.traffic_validation import scripted_clashes, validate

__all__ = ["DT", "Actor", "ActorSet", "TrafficSpec", "simulate_traffic", "validate"]


def simulate_traffic(net: RoadNetwork, world: StaticWorld, ego: EgoMotion, spec: TrafficSpec,
                     shapes: list[ActorShape], rng: np.random.Generator, t_end: float,
                     despawn_distance: float, ego_size=(4.6, 1.9)) -> ActorSet:
    """All actors from time 0 to ``t_end`` (steps of ``DT``): scripted convoy and oncoming
    stream, spawned and simulated traffic, minus the actors that overlap anything.
    Adds the sidewalk loops near the route to ``net`` as ``walk`` tracks."""
    times = np.arange(0.0, t_end + DT / 2, DT)
    ego_radius = float(np.hypot(*ego_size)) / 2
    cars = shapes_of_kind(shapes, "car")
    scripted = [Actor(-1, kind, int(rng.choice(cars)), tr, np.ones(len(times), dtype=bool))
                for kind, tr in scripted_tracks(ego, spec, times)]
    # an oncoming vehicle that would touch the ego or the convoy (tight corners) is left out
    clash = scripted_clashes(scripted, shapes, ego, times, ego_size)
    scripted = [a for a, c in zip(scripted, clash) if not c]
    group = EgoGroup(ego, times, [(a.kind, a.track) for a in scripted], ego_radius)
    prepare_speed_caps(net.tracks)
    agents = spawn_agents(net, world, ego, spec, shapes, rng)
    rec_track, rec_s, alive = run_steps(net, agents, group, times, rng, despawn_distance)
    actors = agents_to_actors(agents, rec_track, rec_s, alive, times, net.tracks)
    actors += scripted
    report: list = []
    removed = validate(actors, shapes, group, world, ego_size, report)
    for k, a in enumerate(actors):
        a.id = labels.ACTOR_ID_BASE + k
    collisions: dict = {}
    for pair in report:
        key = "-".join(pair)
        collisions[key] = collisions.get(key, 0) + 1
    return ActorSet(actors, shapes, times, removed=removed, stats={"collisions": collisions})
