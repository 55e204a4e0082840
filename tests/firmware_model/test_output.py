"""ReceiverOutput's fields are written out; they must be the column record's, in order."""

from __future__ import annotations

import dataclasses
import typing

import numpy as np

from cdma_lidar.column_record import FIELD_NAMES, RECORD
from cdma_lidar.firmware_model import output
from cdma_lidar.firmware_model.output import FIELDS, ReceiverOutput


def test_fields_are_corr_then_the_record_in_record_order():
    names = tuple(f.name for f in dataclasses.fields(ReceiverOutput))
    assert names == FIELDS == ("corr", *FIELD_NAMES)


def test_each_field_is_annotated_with_the_records_dtype():
    hints = typing.get_type_hints(ReceiverOutput, vars(output))
    for f in RECORD:
        (dtype,) = typing.get_args(typing.get_args(hints[f.name])[1])
        assert np.dtype(dtype) == np.dtype(f.dtype), f.name
