"""The Foxglove-native messages: a run as Foxglove's panels draw it.

Each class has the fields and the schema name of one of Foxglove's well-known
schemas (``foxglove.CompressedImage``, ``foxglove.PointCloud``,
``foxglove.ImageAnnotations`` and the geometry they are made of), plus the
dtpf header of :class:`~dtpf.messages.models.Message`, so Foxglove's Image and
3D panels show the channel without any setup. The entity publishes them beside
its own messages (``dtpf/<twin>/entity/cloud``, ``frame``, ``annotations``);
they are part of the wire contract like every other message::

    from dtpf.messages.foxglove import PointCloud
"""
from __future__ import annotations

from typing import Annotated, ClassVar, Literal

from pydantic import AfterValidator, BaseModel, Field

from dtpf.messages.models import BASE64_CHECKED, STRICT_CONFIG, Count, Layer, Message, Time, base64_text

__all__ = ["BASE64_CHECKED", "CircleAnnotation", "Color", "CompressedImage", "ImageAnnotations", "PackedElementField",
           "Point2", "PointCloud", "PointsAnnotation", "Pose", "Quaternion", "Vector3"]


class CompressedImage(Message):
    """One video frame, in the shape of Foxglove's ``foxglove.CompressedImage``: entity -> recorder.

    ``timestamp``, ``frame_id``, ``data`` and ``format`` are Foxglove's
    fields (the MCAP schema is named ``foxglove.CompressedImage``, so
    Foxglove's Image panel shows the channel); the dtpf header comes with
    them. ``data`` is the JPEG or PNG file, standard base64 in JSON.
    """

    producer: ClassVar[Layer] = Layer.ENTITY

    timestamp: Time = Field(description="Time of the frame (the step's publish time).")
    frame_id: str = Field(description="Coordinate frame of the image (the camera).")
    data: Annotated[str, AfterValidator(base64_text)] = Field(
        json_schema_extra={"contentEncoding": "base64"}, description="The compressed image file, base64.")
    format: Literal["jpeg", "png"] = Field(description="Image format: 'jpeg' or 'png'.")


class Vector3(BaseModel):
    """A point or direction in 3-D (Foxglove's ``foxglove.Vector3``)."""

    model_config = STRICT_CONFIG

    x: float = Field(0.0, description="x")
    y: float = Field(0.0, description="y")
    z: float = Field(0.0, description="z")


class Quaternion(BaseModel):
    """A rotation (Foxglove's ``foxglove.Quaternion``); the identity by default."""

    model_config = STRICT_CONFIG

    x: float = Field(0.0, description="x")
    y: float = Field(0.0, description="y")
    z: float = Field(0.0, description="z")
    w: float = Field(1.0, description="w")


class Pose(BaseModel):
    """Position and orientation (Foxglove's ``foxglove.Pose``)."""

    model_config = STRICT_CONFIG

    position: Vector3 = Field(default_factory=Vector3, description="Position.")
    orientation: Quaternion = Field(default_factory=Quaternion, description="Orientation.")


class PackedElementField(BaseModel):
    """One field of a packed point (Foxglove's ``foxglove.PackedElementField``)."""

    model_config = STRICT_CONFIG

    name: str = Field(max_length=64, description="Name of the field (x, y, z, weight).")
    offset: Count = Field(description="Byte offset of the field within a point.")
    type: int = Field(ge=0, le=8, description="Numeric type (Foxglove's NumericType): 8 is FLOAT64.")


#: Most points a cloud message may carry.
MAX_CLOUD_POINTS = 1_000_000


class PointCloud(Message):
    """The particle set of a step as Foxglove's ``foxglove.PointCloud``: entity -> recorder, viewers.

    ``timestamp``, ``frame_id``, ``pose``, ``point_stride``, ``fields`` and
    ``data`` are Foxglove's fields (the MCAP schema is named
    ``foxglove.PointCloud``, so Foxglove's 3D panel shows the particles); the
    dtpf header comes with them. ``data`` is the packed float64 points,
    standard base64.
    """

    producer: ClassVar[Layer] = Layer.ENTITY

    timestamp: Time = Field(description="Time of the step's particle set.")
    frame_id: str = Field(max_length=64, description="Coordinate frame of the points (the state space).")
    pose: Pose = Field(default_factory=Pose, description="Origin of the points: the identity.")
    point_stride: int = Field(ge=1, le=4096, description="Bytes from one point to the next.")
    fields: list[PackedElementField] = Field(max_length=16, description="Fields of each point.")
    data: Annotated[str, AfterValidator(base64_text)] = Field(
        json_schema_extra={"contentEncoding": "base64"}, description="The packed points, base64.")


class Point2(BaseModel):
    """A point in an image, in pixels (Foxglove's ``foxglove.Point2``)."""

    model_config = STRICT_CONFIG

    x: float = Field(description="x, pixels from the left.")
    y: float = Field(description="y, pixels from the top.")


class Color(BaseModel):
    """An RGBA colour, each part in [0, 1] (Foxglove's ``foxglove.Color``)."""

    model_config = STRICT_CONFIG

    r: float = Field(ge=0.0, le=1.0, description="red")
    g: float = Field(ge=0.0, le=1.0, description="green")
    b: float = Field(ge=0.0, le=1.0, description="blue")
    a: float = Field(ge=0.0, le=1.0, description="alpha")


class CircleAnnotation(BaseModel):
    """A circle over an image (Foxglove's ``foxglove.CircleAnnotation``)."""

    model_config = STRICT_CONFIG

    timestamp: Time = Field(description="Time of the image it belongs to.")
    position: Point2 = Field(description="Centre.")
    diameter: float = Field(ge=0.0, description="Diameter in pixels.")
    thickness: float = Field(ge=0.0, description="Line thickness in pixels.")
    fill_color: Color = Field(description="Fill colour.")
    outline_color: Color = Field(description="Outline colour.")


class PointsAnnotation(BaseModel):
    """Points or lines over an image (Foxglove's ``foxglove.PointsAnnotation``)."""

    model_config = STRICT_CONFIG

    timestamp: Time = Field(description="Time of the image it belongs to.")
    type: int = Field(ge=0, le=4, description="0 unknown, 1 points, 2 line loop, 3 line strip, 4 line list.")
    points: list[Point2] = Field(max_length=100_000, description="The points.")
    outline_color: Color = Field(description="Colour of the points or lines.")
    outline_colors: list[Color] = Field(default_factory=list, max_length=100_000,
                                        description="One colour per point (empty: outline_color for all).")
    fill_color: Color = Field(description="Fill colour.")
    thickness: float = Field(ge=0.0, description="Point size or line thickness in pixels.")


#: Most annotations of one kind a message may carry.
MAX_ANNOTATIONS = 1000


class ImageAnnotations(Message):
    """What to draw over a video frame (Foxglove's ``foxglove.ImageAnnotations``): entity -> viewers.

    The video scenario draws each step's particles (their positions) and the
    estimate (its circle) over the frame of the same step and time.
    """

    producer: ClassVar[Layer] = Layer.ENTITY

    circles: list[CircleAnnotation] = Field(default_factory=list, max_length=MAX_ANNOTATIONS,
                                            description="Circles.")
    points: list[PointsAnnotation] = Field(default_factory=list, max_length=MAX_ANNOTATIONS,
                                           description="Point sets and lines.")
