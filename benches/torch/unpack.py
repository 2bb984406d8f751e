"""Unpacks what a GPU machine without Rust or the data is sent (accelerator.sh, memorise.sh):
PACK/ds.xz, an x86-64 `drivescript` compressed with xz, to /tmp/ds, and the tar archive
PACK/ARCHIVE into DEST (emptied first).

    python3 benches/torch/unpack.py PACK ARCHIVE DEST
"""

import lzma
import os
import shutil
import sys
import tarfile

pack, archive, dest = sys.argv[1:4]
with lzma.open(os.path.join(pack, "ds.xz")) as f, open("/tmp/ds", "wb") as g:
    shutil.copyfileobj(f, g)
os.chmod("/tmp/ds", 0o755)
shutil.rmtree(dest, ignore_errors=True)
with tarfile.open(os.path.join(pack, archive)) as t:
    t.extractall(dest)
