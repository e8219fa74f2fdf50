"""Decode bom's bags with the independent Python `rosbags` reader (run by .ci/run).

usage: python tests/check_rosbags.py OUT.mcap INPUT.mcap...
OUT.mcap is an output bag of `bom replay --out`; every message on every topic must decode with
the definitions stored in the file, and the object model must hold at least one joint (and model
criticism, where present, named findings).
"""
import sys
from pathlib import Path

from rosbags.highlevel import AnyReader


def decode_all(path):
    counts = {}
    with AnyReader([Path(path)]) as reader:
        for conn, _, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            counts[conn.topic] = counts.get(conn.topic, 0) + 1
            if conn.topic == "/bom/object_model":
                assert msg.joints, "ObjectModel without joints"
                j = msg.joints[0]
                total = j.p_rigid + j.p_prismatic + j.p_revolute
                assert abs(total - 1.0) < 1e-6, total
                assert j.most_probable_type in ("rigid", "prismatic", "revolute")
            if conn.topic == "/bom/markers":
                assert msg.markers, "empty MarkerArray"
            if conn.topic == "/bom/model_criticism":
                assert msg.findings, "ModelCriticism without findings"
                for f in msg.findings:
                    assert f.effect, "EffectFinding without an effect name"
                    assert len(f.param_names) == len(f.param_values), f.effect
    return counts


def main():
    out, inputs = sys.argv[1], sys.argv[2:]
    counts = decode_all(out)
    for topic in ("/bom/object_model", "/bom/markers", "/bom/predicted_part_poses"):
        assert counts.get(topic, 0) > 0, f"{out}: no {topic}: {counts}"
    print(f"rosbags: {out}: {counts}")
    for path in inputs:
        c = decode_all(path)
        assert c.get("/segmented_points", 0) > 0, f"{path}: {c}"
    print(f"rosbags: {len(inputs)} input bags decode")
    print(f"{1 + len(inputs)} passed, 0 failed")


if __name__ == "__main__":
    main()
