"""The controller's RTDE input side: general purpose registers, digital outputs and the speed slider.

What an input data package does, as Universal Robots' RTDE guide states it:

* ``input_int_register_N`` / ``input_double_register_N`` (N 0..47), ``input_bit_register_N``
  (N 64..127) and the words ``input_bit_registers0_to_31`` / ``input_bit_registers32_to_63`` set the
  general purpose input registers; the guide lists the same names among the outputs, so any client
  reads them back.
* ``standard_digital_output`` (bits 0-7 of ``actual_digital_output_bits``),
  ``configurable_digital_output`` (bits 8-15) and ``tool_digital_output`` (bits 16-17) change only the
  bits set in their ``*_mask`` of the same package.
* ``speed_slider_fraction`` (0..1) sets the speed slider only when ``speed_slider_mask`` = 1 in the
  same package: "0 = don't change speed slider with this input".

No sockets and no controller here: :class:`Registers` is the state, the controller owns one.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

#: (mask name, value name, first bit in actual_digital_output_bits, number of bits)
DIGITAL_OUTPUTS: tuple[tuple[str, str, int, int], ...] = (
    ("standard_digital_output_mask", "standard_digital_output", 0, 8),
    ("configurable_digital_output_mask", "configurable_digital_output", 8, 8),
    ("tool_digital_output_mask", "tool_digital_output", 16, 2),
)

N_INT_REGISTERS = 48
N_DOUBLE_REGISTERS = 48
_WORD = 0xFFFFFFFF


@dataclass
class Registers:
    """Input and output registers, input bits and the digital output bits of the emulated controller."""

    in_int: list[int] = field(default_factory=lambda: [0] * N_INT_REGISTERS)
    in_dbl: list[float] = field(default_factory=lambda: [0.0] * N_DOUBLE_REGISTERS)
    out_int: list[int] = field(default_factory=lambda: [0] * N_INT_REGISTERS)
    out_dbl: list[float] = field(default_factory=lambda: [0.0] * N_DOUBLE_REGISTERS)
    in_bits: int = 0             # input bit registers 0..127 as one integer (bit N = register N)
    digital_out_bits: int = 0    # actual_digital_output_bits

    def apply(self, values: dict[str, Any]) -> float | None:
        """Apply one input data package (name -> value, as the recipe unpacked it).

        Returns:
            The new speed slider fraction (clamped to 0..1) when the package sets it
            (``speed_slider_mask`` = 1 and ``speed_slider_fraction`` in the package), else None.
        """
        for name, value in values.items():
            if name.startswith("input_int_register_"):
                self.in_int[_index(name)] = int(value)
            elif name.startswith("input_double_register_"):
                self.in_dbl[_index(name)] = float(value)
            elif name.startswith("input_bit_register_"):
                bit = 1 << _index(name)
                self.in_bits = (self.in_bits | bit) if value else (self.in_bits & ~bit)
            elif name == "input_bit_registers0_to_31":
                self.in_bits = (self.in_bits & ~_WORD) | (int(value) & _WORD)
            elif name == "input_bit_registers32_to_63":
                self.in_bits = (self.in_bits & ~(_WORD << 32)) | ((int(value) & _WORD) << 32)
        for mask_name, value_name, shift, width in DIGITAL_OUTPUTS:
            if mask_name in values and value_name in values:
                mask = (int(values[mask_name]) & ((1 << width) - 1)) << shift
                new = (int(values[value_name]) << shift) & mask
                self.digital_out_bits = (self.digital_out_bits & ~mask) | new
        if int(values.get("speed_slider_mask", 0)) == 1 and "speed_slider_fraction" in values:
            return max(0.0, min(1.0, float(values["speed_slider_fraction"])))
        return None

    def output(self, name: str) -> Any | None:
        """The value of a register output (``output_*`` / ``input_*`` registers, the digital output
        bits), or None for a name that is not one of them."""
        if name.startswith("output_int_register_"):
            return self.out_int[_index(name)]
        if name.startswith("output_double_register_"):
            return self.out_dbl[_index(name)]
        if name.startswith("input_int_register_"):
            return self.in_int[_index(name)]
        if name.startswith("input_double_register_"):
            return self.in_dbl[_index(name)]
        if name.startswith("input_bit_register_"):
            return bool(self.in_bits >> _index(name) & 1)
        if name == "input_bit_registers0_to_31":
            return self.in_bits & _WORD
        if name == "input_bit_registers32_to_63":
            return (self.in_bits >> 32) & _WORD
        if name == "actual_digital_output_bits":
            return self.digital_out_bits
        return None


def _index(name: str) -> int:
    return int(name.rsplit("_", 1)[1])
