"""Object storage behind one small Protocol: S3 (any endpoint) for the service, the filesystem for local runs."""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

from seasynth.service.errors import NotFound, OutputError, SeasynthError, Unavailable, Unreachable

if TYPE_CHECKING:
    from seasynth.service.settings import Settings


@dataclass(frozen=True)
class ObjectInfo:
    key: str
    bytes: int
    modified: datetime | None = None  # when the object was last written (UTC), where the store says


class ObjectStore(Protocol):
    """Keys are '/'-separated relative paths. Every write is atomic: readers see the old object or the new one."""

    def put_bytes(self, key: str, data: bytes, content_type: str = "application/octet-stream") -> None: ...

    def put_file(self, key: str, path: Path, content_type: str = "application/octet-stream") -> None: ...

    # Writes `data` unless `key` exists (first writer wins, also between concurrent callers); True if written.
    def put_bytes_if_absent(self, key: str, data: bytes, content_type: str = "application/octet-stream") -> bool: ...

    def get_bytes(self, key: str) -> bytes: ...  # NotFound naming the key

    def download(self, key: str, path: Path) -> None: ...  # NotFound naming the key

    def head(self, key: str) -> ObjectInfo | None: ...

    def list(self, prefix: str) -> Iterator[ObjectInfo]: ...  # keys starting with `prefix` (a string prefix, as S3's)

    def delete(self, key: str) -> None: ...  # the one object `key`, if it exists

    def delete_prefix(self, prefix: str) -> int: ...  # objects deleted

    def url(self, key: str) -> str: ...  # where a client can GET the object (presigned for S3)

    def check(self) -> None: ...  # Unavailable when unreachable


def _check_key(key: str) -> str:
    parts = key.split("/")
    if not key or key.startswith("/") or any(p in ("", ".", "..") for p in parts):
        raise ValueError(f"invalid object key {key!r}")
    return key


def _file_info(key: str, path: Path) -> ObjectInfo:
    st = path.stat()
    return ObjectInfo(key, st.st_size, datetime.fromtimestamp(st.st_mtime, UTC))


class LocalStore:
    """Objects as files under `root`; writes go to a temporary file in the same folder, then rename."""

    def __init__(self, root: Path):
        self.root = Path(root).resolve()

    def _path(self, key: str) -> Path:
        return self.root / _check_key(key)

    def _write(self, key: str, write) -> None:
        dest = self._path(key)
        try:
            dest.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(dir=dest.parent, prefix=".tmp-", suffix=dest.name)
            try:
                with os.fdopen(fd, "wb") as f:
                    write(f)
                os.replace(tmp, dest)
            except BaseException:
                Path(tmp).unlink(missing_ok=True)
                raise
        except OSError as err:
            raise OutputError(f"{dest}: cannot write object {key} ({err.strerror or err})") from err

    def put_bytes(self, key: str, data: bytes, content_type: str = "application/octet-stream") -> None:
        self._write(key, lambda f: f.write(data))

    def put_bytes_if_absent(self, key: str, data: bytes, content_type: str = "application/octet-stream") -> bool:
        dest = self._path(key)
        try:
            dest.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(dir=dest.parent, prefix=".tmp-", suffix=dest.name)
            try:
                with os.fdopen(fd, "wb") as f:
                    f.write(data)
                os.link(tmp, dest)  # atomic, and fails if dest exists (os.replace would overwrite)
                return True
            except FileExistsError:
                return False
            finally:
                Path(tmp).unlink(missing_ok=True)
        except OSError as err:
            raise OutputError(f"{dest}: cannot write object {key} ({err.strerror or err})") from err

    def put_file(self, key: str, path: Path, content_type: str = "application/octet-stream") -> None:
        def copy(f) -> None:
            with open(path, "rb") as src:
                while chunk := src.read(1 << 20):
                    f.write(chunk)

        self._write(key, copy)

    def get_bytes(self, key: str) -> bytes:
        try:
            return self._path(key).read_bytes()
        except FileNotFoundError:
            raise NotFound(f"no object {key}") from None

    def download(self, key: str, path: Path) -> None:
        data = self.get_bytes(key)
        path.write_bytes(data)

    def head(self, key: str) -> ObjectInfo | None:
        p = self._path(key)
        return _file_info(key, p) if p.is_file() else None

    def list(self, prefix: str) -> Iterator[ObjectInfo]:
        # A string prefix, as S3 lists: search the deepest folder it names, keep the keys that start with it.
        folder = prefix.rsplit("/", 1)[0] if "/" in prefix else ""
        base = self.root / folder if folder else self.root
        if not base.is_dir():
            return
        for p in sorted(base.rglob("*")):
            if p.is_file() and not p.name.startswith(".tmp-"):
                key = p.relative_to(self.root).as_posix()
                if key.startswith(prefix):
                    yield _file_info(key, p)

    def delete(self, key: str) -> None:
        self._path(key).unlink(missing_ok=True)

    def delete_prefix(self, prefix: str) -> int:
        n = 0
        for info in list(self.list(prefix)):
            self._path(info.key).unlink(missing_ok=True)
            n += 1
        return n

    def url(self, key: str) -> str:
        return self._path(key).as_uri()

    def check(self) -> None:
        if not os.access(self.root if self.root.exists() else self.root.parent, os.W_OK):
            raise Unavailable(f"{self.root}: storage folder is not writable")


class S3Store:
    """A bucket on any S3 endpoint. Small objects go in one PUT; files over the multipart threshold are
    uploaded in parts that become visible only when the upload is completed, so both are atomic."""

    def __init__(self, client, bucket: str, public_client=None, presign_expiry_s: int = 3600):
        self.client = client
        self.bucket = bucket
        self.public_client = public_client or client
        self.presign_expiry_s = presign_expiry_s

    def _fail(self, err: Exception, key: str) -> SeasynthError:
        from botocore.exceptions import ClientError, HTTPClientError
        from botocore.exceptions import ConnectionError as BotoConnectionError

        if isinstance(err, ClientError):
            code = err.response.get("Error", {}).get("Code", "")
            if code in ("404", "NoSuchKey", "NotFound"):
                return NotFound(f"no object {key} in bucket {self.bucket}")
            if err.response.get("ResponseMetadata", {}).get("HTTPStatusCode", 0) >= 500:
                return Unreachable(f"s3://{self.bucket}/{key}: {err}")
        if isinstance(err, (BotoConnectionError, HTTPClientError)):  # refused, reset, timed out
            return Unreachable(f"s3://{self.bucket}/{key}: unreachable: {err}")
        return Unavailable(f"s3://{self.bucket}/{key}: {err}")

    def put_bytes(self, key: str, data: bytes, content_type: str = "application/octet-stream") -> None:
        _check_key(key)
        try:
            self.client.put_object(Bucket=self.bucket, Key=key, Body=data, ContentType=content_type)
        except Exception as err:
            raise self._fail(err, key) from err

    def put_bytes_if_absent(self, key: str, data: bytes, content_type: str = "application/octet-stream") -> bool:
        # S3's conditional write (If-None-Match: *; AWS since 2024, MinIO, moto): 412 when the key exists,
        # 409 while a concurrent conditional write of the key is in flight (then ask again).
        from botocore.exceptions import ClientError

        _check_key(key)
        for _ in range(5):
            try:
                self.client.put_object(Bucket=self.bucket, Key=key, Body=data, ContentType=content_type,
                                       IfNoneMatch="*")
                return True
            except ClientError as err:
                code = err.response.get("Error", {}).get("Code", "")
                status = err.response.get("ResponseMetadata", {}).get("HTTPStatusCode")
                if code == "PreconditionFailed" or status == 412:
                    return False
                if code != "ConditionalRequestConflict" and status != 409:
                    raise self._fail(err, key) from err
            except Exception as err:
                raise self._fail(err, key) from err
        raise Unavailable(f"s3://{self.bucket}/{key}: conditional write kept conflicting with another writer")

    def put_file(self, key: str, path: Path, content_type: str = "application/octet-stream") -> None:
        _check_key(key)
        try:
            self.client.upload_file(
                str(path), self.bucket, key, ExtraArgs={"ContentType": content_type}
            )
        except Exception as err:
            raise self._fail(err, key) from err

    def get_bytes(self, key: str) -> bytes:
        try:
            return self.client.get_object(Bucket=self.bucket, Key=key)["Body"].read()
        except Exception as err:
            raise self._fail(err, key) from err

    def download(self, key: str, path: Path) -> None:
        try:
            self.client.download_file(self.bucket, key, str(path))
        except Exception as err:
            raise self._fail(err, key) from err

    def head(self, key: str) -> ObjectInfo | None:
        try:
            r = self.client.head_object(Bucket=self.bucket, Key=key)
        except Exception as err:
            e = self._fail(err, key)
            if isinstance(e, NotFound):
                return None
            raise e from err
        return ObjectInfo(key, int(r["ContentLength"]), r.get("LastModified"))

    def list(self, prefix: str) -> Iterator[ObjectInfo]:
        try:
            for page in self.client.get_paginator("list_objects_v2").paginate(Bucket=self.bucket, Prefix=prefix):
                for o in page.get("Contents", []):
                    yield ObjectInfo(o["Key"], int(o["Size"]), o.get("LastModified"))
        except Exception as err:
            raise self._fail(err, prefix) from err

    def delete(self, key: str) -> None:
        try:
            self.client.delete_object(Bucket=self.bucket, Key=key)  # no error when there is no such object
        except Exception as err:
            raise self._fail(err, key) from err

    def delete_prefix(self, prefix: str) -> int:
        keys = [o.key for o in self.list(prefix)]
        for i in range(0, len(keys), 1000):
            batch = [{"Key": k} for k in keys[i : i + 1000]]
            try:
                r = self.client.delete_objects(Bucket=self.bucket, Delete={"Objects": batch, "Quiet": True})
            except Exception as err:
                raise self._fail(err, prefix) from err
            # A 200 answer may still list keys it did not delete (Quiet mode reports only those).
            if failed := r.get("Errors"):
                first = failed[0]
                raise Unavailable(
                    f"s3://{self.bucket}/{prefix}: {len(failed)} objects not deleted, e.g. {first.get('Key')} "
                    f"({first.get('Code')}: {first.get('Message')})"
                )
        return len(keys)

    def url(self, key: str) -> str:
        return self.public_client.generate_presigned_url(
            "get_object", Params={"Bucket": self.bucket, "Key": key}, ExpiresIn=self.presign_expiry_s
        )

    def check(self) -> None:
        try:
            self.client.head_bucket(Bucket=self.bucket)
        except Exception as err:
            raise Unavailable(f"bucket {self.bucket} is not reachable: {err}") from err

    def ensure_bucket(self) -> None:
        """Create the bucket unless it exists (SEASYNTH_S3_CREATE_BUCKET); Unreachable when the endpoint is."""
        from botocore.exceptions import ClientError, HTTPClientError
        from botocore.exceptions import ConnectionError as BotoConnectionError

        try:
            self.client.head_bucket(Bucket=self.bucket)
            return
        except ClientError:
            pass
        except (BotoConnectionError, HTTPClientError) as err:
            raise Unreachable(f"bucket {self.bucket} is not reachable: {err}") from err
        region = self.client.meta.region_name
        kwargs = {}
        if region and region != "us-east-1":
            kwargs["CreateBucketConfiguration"] = {"LocationConstraint": region}
        try:
            self.client.create_bucket(Bucket=self.bucket, **kwargs)
        except ClientError as err:
            if err.response.get("Error", {}).get("Code") not in ("BucketAlreadyOwnedByYou", "BucketAlreadyExists"):
                raise Unavailable(f"cannot create bucket {self.bucket}: {err}") from err


def open_store(settings: Settings) -> ObjectStore:
    """The store the settings name; creates the S3 bucket when configured to."""
    if settings.storage == "local":
        return LocalStore(settings.local_root)
    import boto3
    from botocore.config import Config

    cfg = Config(retries={"max_attempts": 5, "mode": "standard"}, signature_version="s3v4")
    session = boto3.session.Session()
    client = session.client("s3", endpoint_url=settings.s3_endpoint_url, config=cfg)
    public = None
    if settings.s3_public_endpoint_url and settings.s3_public_endpoint_url != settings.s3_endpoint_url:
        public = session.client("s3", endpoint_url=settings.s3_public_endpoint_url, config=cfg)
    store = S3Store(client, settings.s3_bucket, public, settings.presign_expiry_s)
    if settings.s3_create_bucket:
        store.ensure_bucket()
    return store
