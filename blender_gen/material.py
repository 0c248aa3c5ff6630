"""Terrain material built from shader nodes, with the Hapke formula generated from ``hapke.py``.

``NodeOps`` is a backend for :func:`crater_core.hapke.radiance_factor`: every arithmetic operator and
function creates a ``ShaderNodeMath`` node, so the shader graph *is* the numpy oracle's formula (one
source of truth). Python floats stay constants (node default values); Cycles folds them.

The material has three modes, selected by two Value nodes the worker sets per render (Cycles folds
constant Value nodes, so the unused branches are compiled away):

- ``hapke`` (direct mode): Diffuse BSDF colour = I/F_Hapke / max(mu0, eps). With the sun lamp's
  strength set so that a white Lambertian surface at normal incidence renders 1 (``sun.SUN_STRENGTH``),
  Cycles then outputs I/F and supplies the cast shadows and the finite solar disk itself.
- ``lit`` (fast mode, terrain-space visibility map): colour = 1 / max(mu0, eps), so Cycles outputs
  the effective illuminated fraction <max(N.l, 0) V(l)>_disk / mu0 (1 fully lit, 0 in shadow).
- ``gbuffer`` (fast mode, camera G-buffer): colour 0 and the sun switched off; only the passes
  (normal, depth, AOVs) matter.

In every mode two AOVs are written: ``P`` (world position) and ``cov`` (1 on terrain), both averaged
over the pixel's samples by Cycles, so P / cov is the mean surface point seen in a pixel and cov
its terrain coverage.

mu0 = N . s (s = unit vector to the sun, a Combine XYZ node set per render), mu = N . I
(I = Geometry Incoming, towards the viewer), cos g = I . s. N is the interpolated shading normal.
"""

from __future__ import annotations

import bpy

from blender_gen import compat
from crater_core import hapke

MU0_EPS = 1e-4  # floor of mu0 in the 1/mu0 colour weights (terminator; r_Hapke ~ mu0 there)
AOV_POSITION = "P"
AOV_COVERAGE = "cov"
MODES = ("hapke", "lit", "gbuffer")


class _Sock:
    """A float output socket of a node in the tree being built; arithmetic makes Math nodes."""

    __slots__ = ("ops", "socket")

    def __init__(self, ops: "NodeOps", socket):
        self.ops = ops
        self.socket = socket

    def __add__(self, o):
        return self.ops.math("ADD", self, o)

    def __radd__(self, o):
        return self.ops.math("ADD", o, self)

    def __sub__(self, o):
        return self.ops.math("SUBTRACT", self, o)

    def __rsub__(self, o):
        return self.ops.math("SUBTRACT", o, self)

    def __mul__(self, o):
        return self.ops.math("MULTIPLY", self, o)

    def __rmul__(self, o):
        return self.ops.math("MULTIPLY", o, self)

    def __truediv__(self, o):
        return self.ops.math("DIVIDE", self, o)

    def __rtruediv__(self, o):
        return self.ops.math("DIVIDE", o, self)

    def __neg__(self):
        return self.ops.math("MULTIPLY", self, -1.0)

    def __pow__(self, p):
        return self.ops.math("POWER", self, p)


class NodeOps:
    """Shader-node backend of :func:`hapke.radiance_factor` (same interface as ``hapke.NumpyOps``)."""

    def __init__(self, node_tree):
        self.tree = node_tree
        self.n_nodes = 0

    # -- plumbing -------------------------------------------------------------------------------
    def wrap(self, socket) -> _Sock:
        return _Sock(self, socket)

    def _input(self, node_input, value):
        if isinstance(value, _Sock):
            self.tree.links.new(value.socket, node_input)
        else:
            node_input.default_value = float(value)

    def math(self, op: str, a, b=None) -> _Sock:
        node = self.tree.nodes.new("ShaderNodeMath")
        node.operation = op
        node.use_clamp = False
        self._input(node.inputs[0], a)
        if b is not None:
            self._input(node.inputs[1], b)
        self.n_nodes += 1
        return _Sock(self, node.outputs[0])

    # -- the functions hapke.radiance_factor uses -------------------------------------------------
    def sqrt(self, x):
        return self.math("SQRT", x)

    def exp(self, x):
        return self.math("EXPONENT", x)

    def cos(self, x):
        return self.math("COSINE", x)

    def sin(self, x):
        return self.math("SINE", x)

    def tan(self, x):
        return self.math("TANGENT", x)

    def arccos(self, x):
        return self.math("ARCCOSINE", x)

    def maximum(self, a, b):
        return self.math("MAXIMUM", a, b)

    def minimum(self, a, b):
        return self.math("MINIMUM", a, b)

    def power(self, x, p):
        return self.math("POWER", x, p)

    def less_equal(self, a, b):
        return 1.0 - self.math("GREATER_THAN", a, b)  # a <= b  <=>  not (a > b)

    def select(self, cond01, a, b):
        return b + cond01 * (a - b)


def _dot(tree, a_socket, b_socket):
    node = tree.nodes.new("ShaderNodeVectorMath")
    node.operation = "DOT_PRODUCT"
    tree.links.new(a_socket, node.inputs[0])
    tree.links.new(b_socket, node.inputs[1])
    return node.outputs["Value"]


def build_terrain_material(params: hapke.HapkeParams, name: str = "terrain_hapke") -> bpy.types.Material:
    """The terrain material (all three modes); see the module docstring."""
    mat = bpy.data.materials.new(name)
    tree = compat.node_tree(mat)
    for node in list(tree.nodes):
        tree.nodes.remove(node)
    ops = NodeOps(tree)

    out = tree.nodes.new("ShaderNodeOutputMaterial")
    out.target = "CYCLES"
    geo = tree.nodes.new("ShaderNodeNewGeometry")
    sun = tree.nodes.new("ShaderNodeCombineXYZ")
    sun.name = sun.label = "sun_dir"
    sun.inputs["Z"].default_value = 1.0
    w_hapke = tree.nodes.new("ShaderNodeValue")
    w_hapke.name = w_hapke.label = "w_hapke"
    w_lit = tree.nodes.new("ShaderNodeValue")
    w_lit.name = w_lit.label = "w_lit"

    mu0 = ops.wrap(_dot(tree, geo.outputs["Normal"], sun.outputs[0]))
    mu = ops.wrap(_dot(tree, geo.outputs["Normal"], geo.outputs["Incoming"]))
    cos_g = ops.wrap(_dot(tree, geo.outputs["Incoming"], sun.outputs[0]))
    radiance_factor = hapke.radiance_factor(mu0, mu, cos_g, params, ops)
    inv_mu0 = 1.0 / ops.maximum(mu0, MU0_EPS)
    colour = (radiance_factor * inv_mu0) * ops.wrap(w_hapke.outputs[0]) + inv_mu0 * ops.wrap(w_lit.outputs[0])

    diffuse = tree.nodes.new("ShaderNodeBsdfDiffuse")
    diffuse.inputs["Roughness"].default_value = 0.0  # Lambertian
    rgb = tree.nodes.new("ShaderNodeCombineColor")
    for ch in ("Red", "Green", "Blue"):
        tree.links.new(colour.socket, rgb.inputs[ch])
    tree.links.new(rgb.outputs[0], diffuse.inputs["Color"])
    tree.links.new(diffuse.outputs[0], out.inputs["Surface"])

    aov_p = tree.nodes.new("ShaderNodeOutputAOV")
    compat.set_aov_name(aov_p, AOV_POSITION)
    tree.links.new(geo.outputs["Position"], aov_p.inputs["Color"])
    aov_c = tree.nodes.new("ShaderNodeOutputAOV")
    compat.set_aov_name(aov_c, AOV_COVERAGE)
    aov_c.inputs["Value"].default_value = 1.0

    mat["hapke_nodes"] = ops.n_nodes
    set_mode(mat, "hapke")
    return mat


def _set(socket, value: float) -> None:
    """Write a node value only when it changes: every write tags the material for a Cycles shader
    re-sync, which recompiles the ~170-node Hapke graph (~0.2 s per render, measured)."""
    if socket.default_value != value:
        socket.default_value = value


def set_sun_direction(mat: bpy.types.Material, to_sun) -> None:
    node = mat.node_tree.nodes["sun_dir"]
    for i, v in enumerate(to_sun):
        _set(node.inputs[i], float(v))


def set_mode(mat: bpy.types.Material, mode: str) -> None:
    if mode not in MODES:
        raise ValueError(f"material mode {mode!r} not in {MODES}")
    nodes = mat.node_tree.nodes
    _set(nodes["w_hapke"].outputs[0], 1.0 if mode == "hapke" else 0.0)
    _set(nodes["w_lit"].outputs[0], 1.0 if mode == "lit" else 0.0)


def register_aovs(view_layer) -> None:
    """Declare the material's AOVs on the view layer (so Cycles writes them as passes)."""
    have = {a.name for a in view_layer.aovs}
    for name, typ in ((AOV_POSITION, "COLOR"), (AOV_COVERAGE, "VALUE")):
        if name not in have:
            aov = view_layer.aovs.add()
            aov.name = name
            aov.type = typ
