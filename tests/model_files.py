"""Model files as the tests edit them: a text or YAML file rewritten in place, joints' position
limits removed, and the five-bar whose distal hinge is modelled as two coaxial hinges welded 6D (a
gauge joint the load must lock)."""

from __future__ import annotations

import re
from pathlib import Path

import yaml

from m3t1r.model.examples import five_bar_files


def edit_text(path: Path, change) -> None:
    """Rewrite a text file by change(text) -> text."""
    text = path.read_text()
    path.write_text(change(text))


def strip_position_limits(urdf: Path, joints: str) -> None:
    """Give every revolute joint whose name matches the regular expression `joints` a <limit> with
    effort and velocity only (URDF requires the element; Pinocchio then reads the range as [0, 0])."""
    edit_text(
        urdf,
        lambda text: re.sub(
            rf'(<joint name="{joints}" type="revolute">(?:(?!</joint>).)*?)<limit[^>]*/>',
            r'\1<limit effort="1" velocity="1"/>',
            text,
            flags=re.S,
        ),
    )


def edit_yaml(path: Path, change) -> None:
    """Rewrite a YAML file by change(document), which edits the loaded document in place."""
    document = yaml.safe_load(path.read_text())
    change(document)
    path.write_text(yaml.safe_dump(document, sort_keys=False))


_CUT_JOINTS = """
  <joint name="cut_1" type="revolute"><parent link="effector"/><child link="cut_link_1"/>
    <origin xyz="0 0 0" rpy="0 0 0"/><axis xyz="0 0 1"/><limit lower="-4" upper="4" effort="1" velocity="1"/></joint>
  <link name="cut_link_1"/>
  <joint name="cut_2" type="revolute"><parent link="tip_2"/><child link="cut_link_2"/>
    <origin xyz="0 0 0" rpy="0 0 0"/><axis xyz="0 0 1"/><limit lower="-4" upper="4" effort="1" velocity="1"/></joint>
  <link name="cut_link_2"/>
</robot>"""


def welded_double_hinge(folder: Path) -> tuple[Path, Path]:
    """The five-bar with its distal hinge modelled as two coaxial hinges, one per chain, welded 6D."""
    urdf, closures = five_bar_files(folder)
    edit_text(urdf, lambda text: text.replace("</robot>", _CUT_JOINTS))

    def weld(document: dict) -> None:
        home = document["home"]
        heading_1, heading_2 = home["motor_1"] + home["elbow_1"], home["motor_2"] + home["elbow_2"]
        home.update(cut_1=0.0, cut_2=heading_1 - heading_2 + 1e-5)  # approximate, as from a CAD export
        document["closures"] = [{"name": "cut", "type": "6D", "frame_a": "cut_link_1", "frame_b": "cut_link_2"}]

    edit_yaml(closures, weld)
    return urdf, closures
