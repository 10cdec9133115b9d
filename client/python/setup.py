# The visq Python client. The protobuf and gRPC stubs are generated here, at
# build time, by the system protoc with grpc_python_plugin: Debian's
# python3-grpc-tools is too old for the proto's explicit `optional` fields,
# and generating with the same protoc as the C++ build keeps one truth.
#
# The stubs land in visq/v1/ (the proto's own package path, so the generated
# `from visq.v1 import visq_pb2` needs no rewriting). The health proto is not
# generated: its path would make a top-level `grpc/` package that shadows
# grpcio's; visq/_health.py speaks its two tiny messages by hand.
#
# Offline install (Debian 12, PEP 668): into a venv that sees Debian's
# python3-grpcio, python3-protobuf and python3-numpy:
#   /usr/bin/python3 -m venv --system-site-packages VENV
#   VENV/bin/pip install --no-build-isolation --no-index ./client/python
# The .proto files are read from ../../proto (this checkout), or from
# $VISQ_PROTO_DIR.
#
# Nothing is written into this folder: setuptools' build/ and visq.egg-info
# go to $VISQ_PYTHON_BUILD_DIR, else to a temporary folder removed at exit
# (pip builds in the source tree since pip 21.3). A wheel, built offline:
#   cmake --build BUILD --target visq_python_wheel   # BUILD/packages/visq-*.whl
# or by hand, with Debian's python3-pip and python3-wheel:
#   python3 -m pip wheel --no-build-isolation --no-index --no-deps -w DIST ./client/python
import atexit
import os
import shutil
import subprocess
import tempfile

from setuptools import setup
from setuptools.command.build_py import build_py

HERE = os.path.dirname(os.path.abspath(__file__))
PROTOS = ["visq/v1/visq.proto"]


def build_dir():
    path = os.environ.get("VISQ_PYTHON_BUILD_DIR")
    if path:
        os.makedirs(path, exist_ok=True)
        return os.path.abspath(path)
    path = tempfile.mkdtemp(prefix="visq-python-build-")
    atexit.register(shutil.rmtree, path, ignore_errors=True)
    return path


BUILD_DIR = build_dir()


def proto_dir():
    root = os.environ.get("VISQ_PROTO_DIR") or os.path.join(HERE, "..", "..", "proto")
    root = os.path.abspath(root)
    for proto in PROTOS:
        if not os.path.isfile(os.path.join(root, proto)):
            raise SystemExit(f"visq: {os.path.join(root, proto)} not found; set VISQ_PROTO_DIR to the "
                             "checkout's proto/ folder")
    return root


def tool(name, package):
    path = shutil.which(name)
    if path is None:
        raise SystemExit(f"visq: {name} not found on PATH (Debian package {package}; deploy/install-deps.sh installs it)")
    return path


class BuildWithStubs(build_py):
    """Generates visq/v1/visq_pb2.py and visq_pb2_grpc.py into the build tree."""

    def run(self):
        super().run()
        out = os.path.abspath(self.build_lib)
        protoc = tool("protoc", "protobuf-compiler")
        plugin = tool("grpc_python_plugin", "protobuf-compiler-grpc")
        root = proto_dir()
        command = [protoc, f"-I{root}", f"--python_out={out}", f"--grpc_out={out}",
                   f"--plugin=protoc-gen-grpc={plugin}"] + [os.path.join(root, p) for p in PROTOS]
        subprocess.run(command, check=True)
        for package in ("visq/v1",):
            init = os.path.join(out, package, "__init__.py")
            if not os.path.exists(init):
                with open(init, "w") as f:
                    f.write("# Generated protobuf and gRPC stubs of visq.v1 (see setup.py).\n")


setup(
    name="visq",
    version="0.1.0",
    description="Python client of visq-server: visibility queries on resident scenes, numpy in and out",
    packages=["visq"],
    python_requires=">=3.9",
    # Debian ships these with egg-info, so pip finds them in a
    # --system-site-packages venv and needs no index.
    install_requires=["grpcio", "protobuf", "numpy"],
    cmdclass={"build_py": BuildWithStubs},
    options={"build": {"build_base": os.path.join(BUILD_DIR, "build")}, "egg_info": {"egg_base": BUILD_DIR}},
)
