"""What the console keeps of a page's annotation text and points (issue 34 §4)."""

from humantele.expert.console.messages import outside_image, plain_text


def test_plain_text_drops_control_and_invisible_format_characters():
    assert plain_text("a\u202eb") == "ab"  # right-to-left override: reverses what follows
    assert plain_text("liver\u200b\u2066x\u2069") == "liverx"  # zero width, isolates
    assert plain_text("\x00a\x1b[31mb\x7f") == "a[31mb"  # NUL, ESC, DEL
    assert plain_text(" left\tkidney\r\n lower  pole ") == "left kidney lower pole"
    assert plain_text("rein gauche, 肾, كلية") == "rein gauche, 肾, كلية"  # any script kept
    assert plain_text("\u202e\u200b") == ""


def test_points_must_be_on_the_image():
    assert outside_image([(0.0, 0.0), (640.0, 480.0)], 640, 480) is None
    assert "outside the 640 x 480 image" in outside_image([(10.0, 10.0), (99000.0, 60.0)],
                                                          640, 480)  # fmt: skip
    assert outside_image([(-0.5, 3.0)], 640, 480) is not None
    assert outside_image([(3.0, 480.5)], 640, 480) is not None


def test_a_page_annotation_arrives_without_control_or_override_characters():
    """Issue 34 §4: annotations kept control characters and U+202E (recorded, listed)."""
    import json
    from collections import Counter

    from humantele.expert.console.messages import PAGE_MESSAGE, Annotation
    from humantele.web.pagesocket import validated

    refused: Counter = Counter()
    text = " left \u202e yendik\x07\n kidney\u200b "
    m = validated(PAGE_MESSAGE, json.dumps({"type": "annotation", "seq": 2, "at": [1.0, 2.0],
                                            "text": text}), refused)  # fmt: skip
    assert isinstance(m, Annotation) and m.text == "left yendik kidney" and not refused
