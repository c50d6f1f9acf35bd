"""The XELA server's messages as raw taxel readings."""
import json

import numpy as np
import pytest

from stages.capture.xela import parse_xela
from stages.markers.uskin import MID_SCALE


def xela_message(data, **extra):
    return json.dumps({"message": 17, "time": 1.7e9, "sensors": 1,
                       "1": {"data": data, "sensor": "1", "taxels": 16, "model": "uSPa44",
                             "calibrated": None, **extra}})


def test_parse_xela_ints_and_hex():
    values = (MID_SCALE + np.arange(48)).tolist()
    expected = np.asarray(values).reshape(16, 3)
    out = parse_xela(xela_message(values, calibrated=[0.1] * 48))
    assert list(out) == ["1"] and out["1"].shape == (16, 3)
    assert np.array_equal(out["1"], expected)
    hexes = [format(v, "04X") for v in values]
    assert np.array_equal(parse_xela(xela_message(hexes))["1"], expected)
    assert np.array_equal(parse_xela(xela_message(",".join(hexes)).encode())["1"], expected)
    msg = json.loads(xela_message(values))
    msg["2"] = {"data": values[::-1]}
    assert np.array_equal(parse_xela(msg)["2"], expected.ravel()[::-1].reshape(16, 3))
    assert parse_xela('{"message": "Welcome"}') == {}


@pytest.mark.parametrize("message, error", [
    ("{not json", r"parse_xela: message is not JSON \(Expecting property name"),
    ("[1, 2]", "parse_xela: message must be a JSON object, got list"),
    (xela_message([1] * 45), r"parse_xela: sensor '1': expected 48 values \(16 taxels x 3\), got 45"),
    (xela_message(["80G0"] * 48), "parse_xela: sensor '1': value '80G0' is not a hex string"),
    (xela_message([1.5] * 48), "parse_xela: sensor '1': value 1.5 is not an integer or a hex string"),
    (xela_message([70000] * 48), r"parse_xela: sensor '1': values outside 0..65535"),
    ('{"3": {"sensor": "3"}}', "parse_xela: sensor '3' has no `data` list"),
])
def test_parse_xela_rejects_malformed(message, error):
    with pytest.raises(ValueError, match=error) as info:
        parse_xela(message)
    assert "\n" not in str(info.value)
