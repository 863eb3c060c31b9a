"""Arm-arm contacts in pick-and-place as the physics sees them (issue 52): which geoms meet
when a run ends in an arm-arm collision, and a render of one where a finger or pad touches.

Reads an ``eval.pickplace`` output directory (its ``summary.json`` settings and
``runs.csv``), re-runs its arm-arm failures on MuJoCo C and records, at the control step
the run ended, every arm-arm contact (geom names, depth). The collision model sees the
gripper as the original's stand-in box (0.09 m along the approach axis); the simulated
fingers and pads reach 0.149 m, so a contact on them is one the kernel could not see.
Writes ``--out`` (PNG: the first such finger contact from two sides, contact points and
forces drawn; only contacts still touching at the end of the control step are seen) and
prints a table (``--json``: one JSON line).

    python benchmarks/pickplace_contact_render.py pp52/s6000_orig --out benchmarks/pickplace_finger_contact.png --json
"""

from __future__ import annotations

import argparse
import csv
import json
import pathlib

import jax
import matplotlib.image
import mujoco
import numpy as np
from common import cpu_name

from mjx_multiarm.pickplace.backends import run_mujoco
from mjx_multiarm.pickplace.plans import plan_runs
from mjx_multiarm.pickplace.render import RunRecorder
from mjx_multiarm.pickplace.scene import ARM, build_scene, collision_model
from mjx_multiarm.planner.policy import Planner

GRIPPER_PARTS = ("finger", "pad")
VIEW_AZIMUTHS = (45.0, 225.0)


def arm_arm_contacts(scene, d: mujoco.MjData) -> list[tuple[str, str, float, np.ndarray]]:
    """(geom, geom, depth m, position) of every touching contact between two arms in ``d``."""
    found = []
    for i in range(d.ncon):
        c = d.contact[i]
        g1, g2 = c.geom1, c.geom2
        if (c.dist < 0 and scene.geom_kind[g1] == ARM and scene.geom_kind[g2] == ARM
                and scene.geom_slot[g1] != scene.geom_slot[g2]):
            found.append((scene.model.geom(g1).name, scene.model.geom(g2).name, float(-c.dist), c.pos.copy()))
    return found


class ContactRecorder(RunRecorder):
    """Keeps each run's arm-arm contacts at its last physics step and a close-up frame of
    the first run whose contact involves a finger or pad."""

    def __init__(self, scene, runs, plans):
        super().__init__(scene.model, runs, plans, every=1, height=480, width=640)
        self.scene, self.contacts, self.image = scene, {}, None
        self.options.flags[mujoco.mjtVisFlag.mjVIS_CONTACTPOINT] = True
        self.options.flags[mujoco.mjtVisFlag.mjVIS_CONTACTFORCE] = True

    def on_step(self, step, datas, state) -> None:
        for r in self.runs:
            found = arm_arm_contacts(self.scene, datas[r])
            if found and r not in self.contacts:
                self.contacts[r] = (step, found)
                gripper = [f for f in found if any(p in f[0] + f[1] for p in GRIPPER_PARTS)]
                if gripper and self.image is None:
                    views = []
                    for azimuth in VIEW_AZIMUTHS:  # close-ups from two sides: one of them sees past the gripper
                        camera = mujoco.MjvCamera()
                        camera.lookat[:] = gripper[0][3]
                        camera.distance, camera.azimuth, camera.elevation = 0.7, azimuth, -40.0
                        self.renderer.update_scene(datas[r], camera, self.options)
                        views.append(self.renderer.render().copy())
                    self.image = (r, step, gripper[0], np.concatenate(views, axis=1))


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run_dir", type=pathlib.Path, help="an eval.pickplace --out directory")
    parser.add_argument("--out", type=pathlib.Path, help="PNG of the first finger or pad contact")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    settings = json.loads((args.run_dir / "summary.json").read_text())["settings"]
    with open(args.run_dir / "runs.csv") as f:
        failed = [int(row["run"]) for row in csv.DictReader(f) if row["cause"] == "arm-arm"]
    print(f"# {cpu_name()}; {len(failed)} arm-arm failures in {args.run_dir}")
    scene = build_scene()
    subset = plan_runs(scene, settings["seed"], failed, None, settings["approach_height"], settings["start_height"],
                       settings["safe"]) if failed else None
    recorder = ContactRecorder(scene, range(len(failed)), subset)
    checkpoint = None if settings["checkpoint"] == "shipped" else settings["checkpoint"]
    if failed:
        arm_xml, obstacles = collision_model()
        policy = Planner.load(checkpoint, safe=settings["safe"], arm_xml=arm_xml, obstacles=obstacles)
        run_mujoco(scene, policy.batched(4), subset, settings["max_steps"], on_step=recorder.on_step)
    recorder.close()
    rows = {failed[k]: {"control_step": step, "pairs": sorted({tuple(sorted((a, b))) for a, b, _, _ in found}),
                        "deepest_mm": 1000 * max(depth for _, _, depth, _ in found)}
            for k, (step, found) in sorted(recorder.contacts.items())}
    gripper = [r for r, row in rows.items() if any(p in a + b for a, b in row["pairs"] for p in GRIPPER_PARTS)]
    for r, row in rows.items():
        print(f"  run {r}: step {row['control_step']}, {row['deepest_mm']:.1f} mm, "
              + "; ".join(f"{a} / {b}" for a, b in row["pairs"]))
    print(f"{len(gripper)} of {len(rows)} arm-arm failures touch a finger or pad")
    report = {"run_dir": str(args.run_dir), "arm_arm_failures": len(failed), "recorded": len(rows),
              "finger_or_pad": len(gripper), "runs": {str(r): row for r, row in rows.items()}}
    if args.out is not None and recorder.image is not None:
        k, step, (a, b, depth, _), image = recorder.image
        args.out.parent.mkdir(parents=True, exist_ok=True)
        matplotlib.image.imsave(args.out, image)
        print(f"wrote {args.out}: run {failed[k]}, control step {step}, {a} / {b}, {1000 * depth:.1f} mm deep")
        report["render"] = {"run": failed[k], "control_step": step, "pair": [a, b]}
    if args.json:
        print(json.dumps(report))


if __name__ == "__main__":
    main()
