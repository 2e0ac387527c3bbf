# One image for every focustrack service (compose.yaml picks the subcommand).
FROM python:3.11-slim

ENV PYTHONUNBUFFERED=1 PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1 MPLBACKEND=Agg
WORKDIR /app

# The package and what its build needs (pyproject names README.md); the generated wire
# code is checked in, so proto/ is not needed at run time.
COPY pyproject.toml README.md ./
COPY focustrack ./focustrack
RUN pip install . && useradd --create-home --uid 10001 focustrack \
    && mkdir -p /data /out && chown focustrack /data /out

USER focustrack
ENTRYPOINT ["focustrack"]
CMD ["--help"]
