"""A PACS over DICOMweb: QIDO-RS search, WADO-RS retrieve, STOW-RS store (``dicomweb-client``).

What the rest of the project sees: :class:`PacsSettings` (URL, credentials, CA bundle: from the
environment or a config file, never from the command line), :class:`Pacs` with
:meth:`Pacs.patients`, :meth:`Pacs.studies`, :meth:`Pacs.series` (plain dataclasses),
:meth:`Pacs.retrieve_series` (the instances of a series written into a private folder, which
the DICOM readers of :mod:`registration.io.dicom` then read like any local series) and
:meth:`Pacs.store` (datasets or files, STOW-RS).

Security:

* credentials come from ``ROADMAP3D_PACS_USERNAME`` / ``ROADMAP3D_PACS_PASSWORD`` or from a
  JSON config file (``ROADMAP3D_PACS_CONFIG``, default ``<user config dir>/roadmap3d/pacs.json``)
  that others cannot read (mode 0600); a URL that carries ``user:password@`` is refused, so a
  password never reaches a command line, a shell history or a log;
* credentials are sent only over HTTPS, or over HTTP to this machine (loopback); HTTPS
  verifies the server against the system's CAs or ``ca_bundle``;
* the ``repr`` of the settings and every error message leave the password out;
* retrieved series land in a folder only the user can read (0700, files 0600), with a bound on
  the number of instances and on the bytes.

Errors are :class:`PacsError` (a ``ValueError``) naming the server and what failed.
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import pydicom
from pydicom.dataset import Dataset

from registration.io.pacs_settings import ENV_URL, PacsError, PacsSettings

__all__ = [
    "ENV_URL",
    "Pacs",
    "PacsError",
    "PacsSettings",
    "PatientEntry",
    "SeriesEntry",
    "StudyEntry",
    "find_series",
]

log = logging.getLogger(__name__)


#: A series holding more instances than this is not retrieved.
MAX_SERIES_INSTANCES = 5000
#: A series larger than this (bytes, as received) is not kept.
MAX_SERIES_BYTES = 4 * 1024**3
#: First wait (milliseconds) before trying a failed request again; doubles each time.
RETRY_WAIT_MS = 500
#: Answers that say "busy, try later": the request is sent again (with the same back-off).
RETRIED_HTTP_CODES = (408, 429, 502, 503, 504)

#: Modalities that hold volumes and X-ray images, for the browser's labels.
VOLUME_MODALITIES = {"CT", "MR"}
XRAY_MODALITIES = {"XA", "RF", "DX"}
RESULT_MODALITIES = {"REG", "OT", "SC"}


# --------------------------------------------------------------------------------------
# What the browser lists
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class PatientEntry:
    patient_id: str
    name: str
    studies: int


@dataclass(frozen=True)
class StudyEntry:
    study_uid: str
    patient_id: str
    patient_name: str
    date: str
    description: str
    modalities: tuple[str, ...]


#: SOP classes of X-ray images and runs (XA, enhanced XA, RF, enhanced XRF) ...
XRAY_SOP_CLASSES = frozenset(
    {"1.2.840.10008.5.1.4.1.1.12.1", "1.2.840.10008.5.1.4.1.1.12.1.1", "1.2.840.10008.5.1.4.1.1.12.2",
     "1.2.840.10008.5.1.4.1.1.12.2.1"}
)  # fmt: skip
#: ... of volumes (CT, enhanced CT, legacy converted enhanced CT, X-ray 3D angiographic/craniofacial) ...
VOLUME_SOP_CLASSES = frozenset(
    {"1.2.840.10008.5.1.4.1.1.2", "1.2.840.10008.5.1.4.1.1.2.1", "1.2.840.10008.5.1.4.1.1.2.2",
     "1.2.840.10008.5.1.4.1.1.13.1.1", "1.2.840.10008.5.1.4.1.1.13.1.2"}
)  # fmt: skip
#: ... and of results (Spatial Registration, Secondary Capture).
RESULT_SOP_CLASSES = frozenset({"1.2.840.10008.5.1.4.1.1.66.1", "1.2.840.10008.5.1.4.1.1.7"})


@dataclass(frozen=True)
class SeriesEntry:
    study_uid: str
    series_uid: str
    modality: str
    description: str
    number: int | None
    instances: int | None
    #: SOP class and NumberOfFrames of the series' first instance ("" / None when unknown).
    sop_class_uid: str = ""
    frames: int | None = None

    @property
    def role(self) -> str:
        """``volume`` (CT/3DRA), ``xray`` (XA/RF image or run), ``result`` (REG, captures) or
        ``other``: by the SOP class of its instances, else by the modality."""
        if self.sop_class_uid in XRAY_SOP_CLASSES:
            return "xray"
        if self.sop_class_uid in VOLUME_SOP_CLASSES:
            return "volume"
        if self.sop_class_uid in RESULT_SOP_CLASSES:
            return "result"
        if self.modality in VOLUME_MODALITIES:
            return "volume"
        if self.modality in XRAY_MODALITIES:
            return "xray"
        if self.modality in RESULT_MODALITIES:
            return "result"
        return "other"

    def label(self) -> str:
        count = "" if self.instances is None else f", {self.instances} instance{'s' * (self.instances != 1)}"
        return f"{self.modality} #{self.number if self.number is not None else '-'} {self.description}{count}".strip()


def _value(item: dict[str, Any], keyword: str) -> Any:
    """A value of a DICOM JSON (PS3.18 F.2) item, by keyword; None when absent."""
    tag = pydicom.datadict.tag_for_keyword(keyword)
    entry = item.get(f"{tag:08X}") if tag is not None else None
    if not entry or not entry.get("Value"):
        return None
    value = entry["Value"][0]
    if isinstance(value, dict):  # person name
        return value.get("Alphabetic", "")
    return value


def _text(item: dict[str, Any], keyword: str) -> str:
    v = _value(item, keyword)
    return "" if v is None else str(v)


def _int(item: dict[str, Any], keyword: str) -> int | None:
    v = _value(item, keyword)
    try:
        return None if v is None else int(v)
    except (TypeError, ValueError):
        return None


def _all(item: dict[str, Any], keyword: str) -> tuple[str, ...]:
    tag = pydicom.datadict.tag_for_keyword(keyword)
    entry = item.get(f"{tag:08X}") if tag is not None else None
    return tuple(str(v) for v in (entry or {}).get("Value", []) or [])


# --------------------------------------------------------------------------------------
# The client
# --------------------------------------------------------------------------------------
class Pacs:
    """A DICOMweb service (QIDO-RS, WADO-RS, STOW-RS under one base URL, e.g. Orthanc's
    ``http://host:8042/dicom-web``)."""

    def __init__(self, settings: PacsSettings) -> None:
        import requests
        from dicomweb_client.api import DICOMwebClient

        self.settings = settings
        session = requests.Session()
        if settings.username is not None:
            session.auth = (settings.username, settings.password or "")
        session.verify = str(settings.ca_bundle) if settings.ca_bundle is not None else True
        session.trust_env = False  # no proxy or .netrc credentials from the environment sneak in
        self._client = DICOMwebClient(settings.url.rstrip("/"), session=session, timeout=settings.timeout_s)
        self._client.set_http_retry_params(
            retry=settings.attempts > 1,
            max_attempts=max(1, settings.attempts),
            wait_exponential_multiplier=RETRY_WAIT_MS,
            retriable_error_codes=RETRIED_HTTP_CODES,
        )

    @property
    def name(self) -> str:
        return self.settings.display_url

    def _call(self, what: str, fn: Any, *args: Any, **kwargs: Any) -> Any:
        """``fn(*args, **kwargs)``, each of its requests tried up to ``settings.attempts`` times by
        the DICOMweb client when the connection fails or times out or the server answers busy
        (408/429/502/503/504), waiting RETRY_WAIT_MS, then twice as long each time. Errors
        become :class:`PacsError` naming the server and the request, never the credentials."""
        import requests
        import retrying

        tries = f" after {self.settings.attempts} attempts" if self.settings.attempts > 1 else ""
        try:
            return fn(*args, **kwargs)
        except PacsError:
            raise
        except requests.exceptions.SSLError:
            raise PacsError(
                f"PACS {self.name}: {what}: the server's certificate is not trusted (give --ca-bundle)"
            ) from None
        except requests.exceptions.HTTPError as exc:
            raise PacsError(_http_error_message(self.name, what, exc.response)) from None
        except retrying.RetryError as exc:  # busy answers until the attempts ran out
            value = exc.last_attempt.value
            response = value if isinstance(value, requests.Response) else None
            raise PacsError(_http_error_message(self.name, what, response) + tries) from None
        except (requests.exceptions.ConnectionError, requests.exceptions.Timeout) as exc:
            kind = "timed out" if isinstance(exc, requests.exceptions.Timeout) else "cannot connect"
            raise PacsError(f"PACS {self.name}: {what}: {kind}{tries} ({type(exc).__name__})") from None
        except requests.exceptions.RequestException as exc:
            raise PacsError(f"PACS {self.name}: {what}: request failed ({type(exc).__name__})") from None
        except (ValueError, KeyError, TypeError) as exc:
            raise PacsError(f"PACS {self.name}: {what}: unusable answer ({exc})") from None

    # ----- QIDO-RS -------------------------------------------------------------------
    def studies(self, patient_id: str | None = None) -> list[StudyEntry]:
        """Every study (of one patient when ``patient_id`` is given), newest first."""
        filters = {"PatientID": patient_id} if patient_id else None
        fields = ["PatientID", "PatientName", "StudyDate", "StudyDescription", "ModalitiesInStudy"]
        items = self._call(
            "searching studies",
            self._client.search_for_studies,
            fields=fields,
            search_filters=filters,
            get_remaining=True,
        )
        out = [
            StudyEntry(
                study_uid=_text(i, "StudyInstanceUID"),
                patient_id=_text(i, "PatientID"),
                patient_name=_text(i, "PatientName"),
                date=_text(i, "StudyDate"),
                description=_text(i, "StudyDescription"),
                modalities=_all(i, "ModalitiesInStudy"),
            )
            for i in items
        ]
        return sorted((s for s in out if s.study_uid), key=lambda s: (s.date, s.study_uid), reverse=True)

    def patients(self) -> list[PatientEntry]:
        """The patients of the stored studies (QIDO-RS has no patient level: grouped from studies)."""
        counts: dict[str, list[Any]] = {}
        for s in self.studies():
            entry = counts.setdefault(s.patient_id, [s.patient_name, 0])
            entry[1] += 1
        return [PatientEntry(pid, name, n) for pid, (name, n) in sorted(counts.items())]

    def series(self, study_uid: str) -> list[SeriesEntry]:
        """The series of a study, by series number."""
        fields = ["Modality", "SeriesDescription", "SeriesNumber", "NumberOfSeriesRelatedInstances"]
        items = self._call(
            f"listing the series of study {study_uid}",
            self._client.search_for_series,
            study_instance_uid=study_uid,
            fields=fields,
            get_remaining=True,
        )
        out = []
        for i in items:
            series_uid = _text(i, "SeriesInstanceUID")
            if not series_uid:
                continue
            first = self._call(
                f"looking into series {series_uid}",
                self._client.search_for_instances,
                study_instance_uid=study_uid,
                series_instance_uid=series_uid,
                fields=["SOPClassUID", "NumberOfFrames"],
                limit=1,
            )
            out.append(
                SeriesEntry(
                    study_uid=study_uid,
                    series_uid=series_uid,
                    modality=_text(i, "Modality"),
                    description=_text(i, "SeriesDescription"),
                    number=_int(i, "SeriesNumber"),
                    instances=_int(i, "NumberOfSeriesRelatedInstances"),
                    sop_class_uid=_text(first[0], "SOPClassUID") if first else "",
                    frames=(_int(first[0], "NumberOfFrames") or 1) if first else None,
                )
            )
        return sorted(out, key=lambda s: (s.number is None, s.number or 0, s.series_uid))

    def frames(self, study_uid: str, series_uid: str) -> int:
        """The largest NumberOfFrames of the series' instances (1 for single-frame images)."""
        items = self._call(
            f"listing the instances of series {series_uid}",
            self._client.search_for_instances,
            study_instance_uid=study_uid,
            series_instance_uid=series_uid,
            fields=["NumberOfFrames"],
            get_remaining=True,
        )
        return max([_int(i, "NumberOfFrames") or 1 for i in items] or [0])

    # ----- WADO-RS -------------------------------------------------------------------
    def retrieve_series(self, study_uid: str, series_uid: str, folder: str | os.PathLike[str] | None = None) -> Path:
        """Write the series' instances into ``folder`` (default: a new private temporary folder)
        as ``NNNN.dcm`` and return the folder. The caller removes a temporary folder."""
        instances = self._call(
            f"listing the instances of series {series_uid}",
            self._client.search_for_instances,
            study_instance_uid=study_uid,
            series_instance_uid=series_uid,
            fields=["SOPInstanceUID"],
            get_remaining=True,
        )
        if not instances:
            raise PacsError(f"PACS {self.name}: series {series_uid} of study {study_uid} holds no instance")
        if len(instances) > MAX_SERIES_INSTANCES:
            raise PacsError(
                f"PACS {self.name}: series {series_uid} holds {len(instances)} instances "
                f"(more than {MAX_SERIES_INSTANCES}); refused"
            )
        created = folder is None
        out = Path(folder) if folder is not None else Path(tempfile.mkdtemp(prefix="roadmap3d-pacs-"))
        out.mkdir(parents=True, exist_ok=True)
        out.chmod(0o700)

        def fetch() -> tuple[int, int]:
            # one instance in memory at a time: each is written as it arrives
            count, size = 0, 0
            for ds in self._client.iter_series(study_uid, series_uid):
                if count >= MAX_SERIES_INSTANCES:
                    raise PacsError(
                        f"PACS {self.name}: series {series_uid} sends more than {MAX_SERIES_INSTANCES} instances"
                    )
                path = out / f"{count:04d}.dcm"
                _save(ds, path)
                count += 1
                size += path.stat().st_size
                if size > MAX_SERIES_BYTES:
                    raise PacsError(f"PACS {self.name}: series {series_uid} exceeds {MAX_SERIES_BYTES} bytes; refused")
            return count, size

        try:
            count, total = self._call(f"retrieving series {series_uid}", fetch)
        except BaseException:
            if created:
                shutil.rmtree(out, ignore_errors=True)
            raise
        if count == 0:
            raise PacsError(f"PACS {self.name}: series {series_uid} sent no instance")
        log.info("retrieved %d instances (%d bytes) of series %s from %s", count, total, series_uid, self.name)
        return out

    # ----- STOW-RS -------------------------------------------------------------------
    def store(self, items: Iterable[Dataset | str | os.PathLike[str]]) -> int:
        """Store datasets (or DICOM files) with STOW-RS, one request per study; the number stored."""
        datasets: list[Dataset] = []
        for item in items:
            if isinstance(item, Dataset):
                datasets.append(item)
            else:
                datasets.append(pydicom.dcmread(item))
        by_study: dict[str, list[Dataset]] = {}
        for ds in datasets:
            by_study.setdefault(str(ds.StudyInstanceUID), []).append(ds)
        stored = 0
        for study_uid, group in by_study.items():
            answer = self._call(
                f"storing {len(group)} instance(s) into study {study_uid}",
                self._client.store_instances,
                datasets=group,
                study_instance_uid=study_uid,
            )
            failed = answer.get("FailedSOPSequence") if answer is not None else None
            if failed:
                reasons = sorted({str(f.get("FailureReason", "?")) for f in failed})
                raise PacsError(
                    f"PACS {self.name}: {len(failed)} of {len(group)} instance(s) refused "
                    f"(reasons {', '.join(reasons)})"
                )
            stored += len(group)
        log.info("stored %d instance(s) on %s", stored, self.name)
        return stored


def _http_error_message(server: str, what: str, response: Any) -> str:
    """What an HTTP error answer means, naming the server and the request (method and path,
    without query or credentials)."""
    code = response.status_code if response is not None else "?"
    request = ""
    if response is not None and response.request is not None:
        path = urlsplit(str(response.request.url or "")).path
        request = f" ({response.request.method} {path})"
    if code in (401, 403):
        hint = "wrong or missing credentials" if code == 401 else "the account may not do this"
    elif code == 404:
        hint = "not found on the server"
    elif isinstance(code, int) and code >= 500:
        hint = "the server failed; try again later or ask its administrator"
    else:
        hint = "refused by the server"
    return f"PACS {server}: {what}: HTTP {code} ({hint}){request}"


def _save(ds: Dataset, path: Path) -> None:
    """Write a retrieved dataset as a DICOM file only the user can read."""
    from pydicom.dataset import FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian

    meta = getattr(ds, "file_meta", None) or FileMetaDataset()
    meta.MediaStorageSOPClassUID = ds.SOPClassUID
    meta.MediaStorageSOPInstanceUID = ds.SOPInstanceUID
    if "TransferSyntaxUID" not in meta:
        meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds.file_meta = meta
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "wb") as fh:
        ds.save_as(fh, enforce_file_format=True)


def find_series(series: Sequence[SeriesEntry], role: str) -> SeriesEntry | None:
    """The first series of a study with the given :attr:`SeriesEntry.role`, or None."""
    return next((s for s in series if s.role == role), None)
