"""The served leaderboard's database (SQLAlchemy 2.x): submitter tokens and accepted submissions.

SQLite by default (a file next to where the server runs); any SQLAlchemy URL works, e.g.
``postgresql+psycopg://user@host/dbname`` for a hosted board. Tokens are high-entropy random
strings stored only as their sha256 and compared with ``hmac.compare_digest``. An accepted
submission is one row *and* one store file: :meth:`Database.add_submission` commits the row only
after the file is in place and removes the file when the commit fails, so the two never disagree.
"""

from __future__ import annotations

import hashlib
import hmac
import re
import secrets
import threading
from pathlib import Path

from sqlalchemy import Boolean, Integer, String, Text, UniqueConstraint, create_engine, delete, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import DeclarativeBase, Mapped, Session, mapped_column

from leaderboard.store import DuplicateSubmissionError, store_path, write_submission
from leaderboard.submission import Submission, canonical_json
from offdyn_bench.errors import OffdynError

TOKEN_BYTES = 32
_TOKEN_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9 ._@+-]{0,63}$")


class Base(DeclarativeBase):
    pass


class TokenRow(Base):
    __tablename__ = "tokens"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    name: Mapped[str] = mapped_column(String(64), unique=True)
    token_sha256: Mapped[str] = mapped_column(String(64), unique=True)
    active: Mapped[bool] = mapped_column(Boolean, default=True)


class SubmissionRow(Base):
    __tablename__ = "submissions"
    __table_args__ = (UniqueConstraint("method", "track", "budget", name="one_entry_per_method_track_budget"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    method: Mapped[str] = mapped_column(String(48))
    track: Mapped[str] = mapped_column(String(32))
    budget: Mapped[str] = mapped_column(String(32))
    file_name: Mapped[str] = mapped_column(String(160), unique=True)
    sha256: Mapped[str] = mapped_column(String(64))
    """sha256 of the store file's bytes."""
    submitter: Mapped[str] = mapped_column(String(64))
    document: Mapped[str] = mapped_column(Text)


def hash_token(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


class Database:
    def __init__(self, url: str) -> None:
        from sqlalchemy.exc import ArgumentError, NoSuchModuleError, OperationalError

        try:
            self.engine = create_engine(url)
            Base.metadata.create_all(self.engine)
        except (ArgumentError, NoSuchModuleError) as error:
            raise OffdynError(f"cannot use database URL {url!r} ({error}); expected e.g. "
                              "sqlite:///leaderboard.sqlite3 or postgresql+psycopg://user@host/dbname") from None
        except OperationalError as error:
            raise OffdynError(f"cannot open database {url!r}: {error.orig}") from None
        # One writer at a time within a server process: the duplicate check, the row and the
        # file form one step. Across processes the unique constraint still refuses a duplicate.
        self._write_lock = threading.Lock()

    # Tokens ---------------------------------------------------------------------------------

    def create_token(self, name: str) -> str:
        """A new token for ``name``; only its sha256 is stored, so this is the one chance to show it."""
        if not _TOKEN_NAME.match(name):
            raise OffdynError(f"token name {name!r}: expected 1-64 letters, digits, spaces or . _ @ + - "
                              "(starting with a letter or digit)")
        token = secrets.token_urlsafe(TOKEN_BYTES)
        with Session(self.engine) as session:
            session.add(TokenRow(name=name, token_sha256=hash_token(token), active=True))
            try:
                session.commit()
            except IntegrityError:
                raise OffdynError(f"a token named {name!r} exists; revoke it first or choose another name") from None
        return token

    def revoke_token(self, name: str) -> None:
        with Session(self.engine) as session:
            removed = session.execute(delete(TokenRow).where(TokenRow.name == name)).rowcount
            session.commit()
        if not removed:
            raise OffdynError(f"no token named {name!r}")

    def submitter_of(self, token: str) -> str | None:
        """The name behind ``token``, or None. Every stored hash is compared in constant time."""
        presented = hash_token(token)
        with Session(self.engine) as session:
            rows = session.execute(select(TokenRow.name, TokenRow.token_sha256).where(TokenRow.active)).all()
        found = None
        for name, stored in rows:
            if hmac.compare_digest(presented, stored):
                found = name
        return found

    # Submissions ----------------------------------------------------------------------------

    def submission_keys(self) -> list[tuple[str, str, str]]:
        with Session(self.engine) as session:
            rows = session.execute(select(SubmissionRow.method, SubmissionRow.track, SubmissionRow.budget)
                                   .order_by(SubmissionRow.file_name)).all()
        return [tuple(row) for row in rows]  # type: ignore[misc]

    def add_submission(self, submission: Submission, store: Path, submitter: str) -> Path:
        """Record ``submission`` in the database and the store, both or neither."""
        data = canonical_json(submission.document)
        path = store_path(store, submission)
        with self._write_lock, Session(self.engine) as session:
            session.add(SubmissionRow(method=submission.method, track=submission.track, budget=submission.budget,
                                      file_name=path.name, sha256=hashlib.sha256(data).hexdigest(),
                                      submitter=submitter, document=data.decode()))
            try:
                session.flush()
            except IntegrityError:
                session.rollback()
                raise DuplicateSubmissionError(f"{submission.method} already has an entry on the {submission.track} "
                                               f"track, {submission.budget} budget; a method has one entry per "
                                               "track and budget") from None
            try:
                written = write_submission(store, submission)
            except BaseException:
                session.rollback()
                raise
            try:
                session.commit()
            except BaseException:
                written.unlink(missing_ok=True)
                raise
        return written

