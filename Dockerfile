# bradyscope: web app + embedded worker. Scale out with more containers running
# `bradyscope worker` against the same PostgreSQL (BRADYSCOPE_DATABASE_URL).
FROM python:3.11-slim-bookworm

# Pango and a font for WeasyPrint's PDF reports; a C compiler for the compiled
# marker search and the serial part's loops (core/_blobs.pyx, core/_geometry.pyx,
# core/_tracks.pyx),
# removed again after the install below.
RUN apt-get update \
 && apt-get install -y --no-install-recommends libpango-1.0-0 libpangoft2-1.0-0 libharfbuzz0b \
      libharfbuzz-subset0 libfontconfig1 libglib2.0-0 fonts-dejavu-core gcc libc6-dev \
 && rm -rf /var/lib/apt/lists/*

RUN useradd --create-home --uid 10001 bradyscope
WORKDIR /srv/bradyscope
COPY pyproject.toml setup.py README.md ./
COPY core core
COPY app app
COPY templates templates
COPY migrations migrations
# Editable install: templates/ and migrations/ are read from this folder.
RUN pip install --no-cache-dir -e . \
 && apt-get purge -y --auto-remove gcc libc6-dev

ENV BRADYSCOPE_DATA_DIR=/data
RUN mkdir -p /data && chown bradyscope /data
VOLUME ["/data"]
USER bradyscope
EXPOSE 8000
CMD ["bradyscope", "serve", "--host", "0.0.0.0", "--port", "8000"]
