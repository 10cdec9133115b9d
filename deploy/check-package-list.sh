#!/usr/bin/env bash
# check-package-list.sh BUILD_DIR
# Proves deploy/install-deps.sh's package list complete for a finished build
# (CMake, Unix Makefiles generator): every system file the build read must
# belong to a listed package, to an Essential package, or to a package in
# their installed Depends/Pre-Depends closure. A package the development
# machine happens to have is otherwise invisible until a clean machine fails.
#
# The files the build read, outside the source tree and BUILD_DIR:
#   - every header in the compiler's dependency files (*.o.d);
#   - every library on the link lines (CMakeFiles/*.dir/link.txt): absolute
#     .so/.a paths, and -lNAME resolved as the linker does (-L, then the
#     compiler's own search directories);
#   - every CMake file configure read (CMAKE_MAKEFILE_DEPENDS: package config
#     files, find modules), and every file configure found (FILEPATH entries
#     of CMakeCache.txt, such as OPENGL_opengl_LIBRARY) except the few that
#     find modules look for without CMakeLists.txt requiring them.
# A symlink counts twice: the link's package (libfoo-dev for libfoo.so) and
# its target's (libfoo1). /lib, /bin and /sbin are merged with /usr: a path is
# looked up in both spellings. Alternatives a | b in Depends follow every
# alternative that is installed; a virtual package, its installed providers.
# Prints each package that is needed but not covered, with one file that
# needs it, and exits 1. Runs in a few seconds (one dpkg-query for the
# owners, one for the dependency graph).
set -euo pipefail
export LC_ALL=C

if [[ $# -ne 1 || ! -f "$1/CMakeCache.txt" ]]; then
  echo "usage: $0 BUILD_DIR (a configured and built CMake build directory)" >&2
  exit 2
fi
start=$(date +%s%N)
here=$(cd "$(dirname "$0")" && pwd)
build=$(cd "$1" && pwd -P)
source_dir=$(sed -n 's/^CMAKE_HOME_DIRECTORY:INTERNAL=//p' "$build/CMakeCache.txt")
source_dir=$(cd "${source_dir:-$here/..}" && pwd -P)
tmp=$(mktemp -d)
# VISQ_CHECK_KEEP=DIR keeps the intermediate lists (files read, owners, covered packages) there.
trap 'if [[ -n "${VISQ_CHECK_KEEP:-}" ]]; then rm -rf "$VISQ_CHECK_KEEP"; cp -r "$tmp" "$VISQ_CHECK_KEEP"; fi; rm -rf "$tmp"' EXIT

# FILEPATH cache entries that FindOpenGL fills in when the file exists; visq
# requires only the EGL and OpenGL components.
optional_cache='^(OPENGL_glu_LIBRARY|OPENGL_gl_LIBRARY|OPENGL_glx_LIBRARY|OPENGL_GLES2_LIBRARY|OPENGL_GLES3_LIBRARY)$'

# --- 1. What the build read: "path<TAB>what read it", one a line ------------
find "$build" -path '*/CMakeFiles/*' -name '*.o.d' -type f > "$tmp/depfiles"
if [[ ! -s "$tmp/depfiles" ]]; then
  echo "check-package-list: no compiler dependency files (*.o.d) under $build: build it first (Unix Makefiles generator)" >&2
  exit 2
fi
# Depfiles: "target: dep dep \" continued; a relative path is relative to the
# directory the Makefile generator compiles in (the part before /CMakeFiles/).
tr '\n' '\0' < "$tmp/depfiles" | xargs -0 awk '
  FNR == 1 { base = FILENAME; sub(/\/CMakeFiles\/.*/, "", base)
             origin = FILENAME; sub(/.*\/CMakeFiles\//, "", origin); sub(/\.d$/, "", origin)
             sub(/^[^ ]*: */, "") }
  { gsub(/\\ /, "\001"); n = split($0, t, /[ \t]+/)
    for (i = 1; i <= n; i++) {
      p = t[i]; if (p == "" || p == "\\" || p ~ /:$/) continue   # -MP phony targets end in ":"
      gsub("\001", " ", p); if (substr(p, 1, 1) != "/") p = base "/" p
      print p "\t" origin } }' > "$tmp/read"

# Link lines of executables and shared libraries (static ones only run ar).
find "$build" -path '*/CMakeFiles/*.dir/link.txt' -type f > "$tmp/linkfiles"
: > "$tmp/lnames"; : > "$tmp/ldirs"
if [[ -s "$tmp/linkfiles" ]]; then
  tr '\n' '\0' < "$tmp/linkfiles" | xargs -0 awk -v lnames="$tmp/lnames" -v ldirs="$tmp/ldirs" '
    FNR == 1 { origin = FILENAME; sub(/.*\/CMakeFiles\//, "", origin); sub(/\/link\.txt$/, "", origin) }
    { for (i = 2; i <= NF; i++) {
        p = $i; gsub(/^"|"$/, "", p)
        if (p ~ /^\// && p ~ /\.(a|so(\.[0-9]+)*)$/) print p "\t" origin
        else if (p ~ /^-L\//) print substr(p, 3) > ldirs
        else if (p ~ /^-l./) print substr(p, 3) "\t" origin > lnames } }' >> "$tmp/read"
  # -lNAME as ld finds it: the -L directories, then the compiler's own.
  compiler=$(sed -n 's/^CMAKE_CXX_COMPILER:[A-Z]*=//p' "$build/CMakeCache.txt")
  mapfile -t dirs < <(sort -u "$tmp/ldirs"
    "$compiler" -print-search-dirs 2>/dev/null | sed -n 's/^libraries: =//p' | tr ':' '\n')
  declare -A seen=()
  while IFS=$'\t' read -r name origin; do
    [[ -n "${seen[$name]:-}" ]] && continue
    seen[$name]=1
    if [[ "$name" == :* ]]; then candidates=("${name#:}"); else candidates=("lib$name.so" "lib$name.a"); fi
    found=
    for d in "${dirs[@]}"; do
      for c in "${candidates[@]}"; do
        if [[ -e "$d/$c" ]]; then found="$d/$c"; break 2; fi
      done
    done
    if [[ -n "$found" ]]; then
      printf '%s\t%s (-l%s)\n' "$found" "$origin" "$name" >> "$tmp/read"
    else
      printf 'check-package-list: cannot resolve -l%s (%s) in %s\n' "$name" "$origin" "${dirs[*]}" >&2
      echo "-l$name" >> "$tmp/unresolved"
    fi
  done < "$tmp/lnames"
fi

# What configure read and found.
if [[ -f "$build/CMakeFiles/Makefile.cmake" ]]; then
  awk '/^set\(CMAKE_MAKEFILE_DEPENDS/ { on = 1; next } on && /^ *\)/ { on = 0 }
       on { p = $1; gsub(/"/, "", p); if (p ~ /^\//) print p "\tconfigure" }' \
    "$build/CMakeFiles/Makefile.cmake" >> "$tmp/read"
fi
awk -F '=' -v optional="$optional_cache" '
  /^[A-Za-z0-9_.+-]+:FILEPATH=\// { name = $1; sub(/:FILEPATH$/, "", name)
    if (name !~ optional) print substr($0, index($0, "=") + 1) "\tCMakeCache.txt " name }' \
  "$build/CMakeCache.txt" >> "$tmp/read"
sed -n 's/^\(CMAKE_COMMAND\|CMAKE_CTEST_COMMAND\):INTERNAL=\(\/.*\)/\2\tCMakeCache.txt \1/p' "$build/CMakeCache.txt" >> "$tmp/read"

# --- 2. System files only, each once; the symlink and its target -----------
# lexical path (.. removed, symlinks kept) <TAB> fully resolved path <TAB> origin
cut -f1 "$tmp/read" | tr '\n' '\0' | xargs -0 realpath -s -m -- > "$tmp/lexical"
cut -f1 "$tmp/read" | tr '\n' '\0' | xargs -0 realpath -m -- > "$tmp/canonical"
cut -f2 "$tmp/read" | paste "$tmp/lexical" "$tmp/canonical" - |
  awk -F '\t' -v src="$source_dir/" -v bld="$build/" '
    function inside(p) { return index(p "/", src) == 1 || index(p "/", bld) == 1 }
    !inside($1) && !inside($2) && !seen[$1]++' > "$tmp/files"

# --- 3. The owner of every path, in one dpkg-query -------------------------
# Both spellings of merged-usr paths: dpkg records libc6's files under /lib,
# the compiler reports /usr/lib (and the reverse for other packages).
awk -F '\t' '
  function both(p) { print p
    if (p ~ /^\/usr\/(lib|lib32|lib64|libx32|bin|sbin)\//) print substr(p, 5)
    else if (p ~ /^\/(lib|lib32|lib64|libx32|bin|sbin)\//) print "/usr" p }
  { both($1); if ($2 != $1) both($2) }' "$tmp/files" | sort -u > "$tmp/queries"
# A path no package owns is reported on stderr; an answer "diversion by ..." is not an owner.
tr '\n' '\0' < "$tmp/queries" | xargs -0 dpkg-query -S -- 2>/dev/null |
  awk '!/^diversion by / { i = index($0, ": /"); if (i == 0) next
         owners = substr($0, 1, i - 1); path = substr($0, i + 2)
         n = split(owners, o, /, */)
         for (k = 1; k <= n; k++) { sub(/:.*/, "", o[k]); print path "\t" o[k] } }' > "$tmp/owners" || true

# --- 4. The packages the list covers: listed, Essential, and their closure --
bash "$here/install-deps.sh" --print > "$tmp/listed"
dpkg-query -W -f='${db:Status-Abbrev}\t${Package}\t${Essential}\t${Provides}\t${Depends}, ${Pre-Depends}\n' > "$tmp/installed"
awk -F '\t' '
  function names(field, out,   n, i, a) {   # "a (>= 1) | b:any, c" -> clauses of names
    n = split(field, a, /, */)
    for (i = 1; i <= n; i++) { gsub(/\([^)]*\)|\[[^]]*\]|<[^>]*>|:[a-z0-9]+/, "", a[i]); gsub(/ /, "", a[i]); out[i] = a[i] }
    return n }
  FILENAME == ARGV[1] { listed[$1] = 1; next }
  $1 !~ /^.i/ { next }
  { pkg = $2; installed[pkg] = 1; deps[pkg] = $5
    if ($3 == "yes") listed[pkg] = 1
    n = names($4, prov); for (i = 1; i <= n; i++) if (prov[i] != "") providers[prov[i]] = providers[prov[i]] " " pkg }
  END {
    # A listed package that an installed one provides (install-deps.sh counts
    # it present: NodeSource nodejs provides npm) stands for its providers.
    for (p in listed) if (p in installed) { queue[++tail] = p; covered[p] = 1 }
      else if (p in providers) { k = split(providers[p], c, / /)
        for (q = 1; q <= k; q++) if (c[q] in installed && !(c[q] in covered)) { covered[c[q]] = 1; queue[++tail] = c[q] } }
      else print "check-package-list: listed package " p " is not installed (run deploy/install-deps.sh)" > "/dev/stderr"
    for (head = 1; head <= tail; head++) {
      n = names(deps[queue[head]], clause)
      for (i = 1; i <= n; i++) {
        m = split(clause[i], alt, /\|/)
        for (j = 1; j <= m; j++) {
          cand = alt[j]; if (cand in providers) cand = cand providers[cand]
          k = split(cand, c, / /)
          for (q = 1; q <= k; q++) if (c[q] in installed && !(c[q] in covered)) { covered[c[q]] = 1; queue[++tail] = c[q] } } } }
    for (p in covered) print p }' "$tmp/listed" "$tmp/installed" > "$tmp/covered"

# --- 5. Every file: each of its ends needs an owner that is covered ---------
awk -F '\t' '
  function twin(p) { if (p ~ /^\/usr\/(lib|lib32|lib64|libx32|bin|sbin)\//) return substr(p, 5)
                     if (p ~ /^\/(lib|lib32|lib64|libx32|bin|sbin)\//) return "/usr" p; return p }
  function owners_of(p) { return owner[p] owner[twin(p)] }
  function check(p, origin,   os, n, i, ok, first) {   # 0: no owner; 1: fine; 2: not covered
    os = owners_of(p); if (os == "") return 0
    n = split(os, o, / /); ok = 0; first = ""
    for (i = 1; i <= n; i++) if (o[i] != "") { if (first == "") first = o[i]; if (o[i] in covered) ok = 1 }
    if (!ok && !(first in missing)) { missing[first] = p " (" origin ")"; order[++nmissing] = first }
    return ok ? 1 : 2 }
  FILENAME == ARGV[1] { covered[$1] = 1; next }
  FILENAME == ARGV[2] { if (index(" " owner[$1] " ", " " $2 " ") == 0) owner[$1] = owner[$1] " " $2; next }
  { nfiles++
    a = check($1, $3); b = ($2 != $1) ? check($2, $3) : 0
    if (a == 0 && b == 0) { unowned[++nunowned] = $1 " (" $3 ")" } }
  END {
    for (i = 1; i <= nmissing; i++) printf "MISSING %s\t%s\n", order[i], missing[order[i]]
    for (i = 1; i <= nunowned; i++) printf "UNOWNED %s\n", unowned[i]
    printf "FILES %d\n", nfiles }' "$tmp/covered" "$tmp/owners" "$tmp/files" > "$tmp/result"

files=$(sed -n 's/^FILES //p' "$tmp/result")
npackages=$(wc -l < "$tmp/listed")
ms=$(( ($(date +%s%N) - start) / 1000000 ))
status=0
if grep -q '^MISSING ' "$tmp/result"; then
  echo "check-package-list: packages the build needs that deploy/install-deps.sh does not list (nor any listed package depends on):"
  awk -F '\t' 'sub(/^MISSING /, "") { printf "  %-24s e.g. %s\n", $1, $2 }' "$tmp/result" | sort
  status=1
fi
if grep -q '^UNOWNED ' "$tmp/result"; then
  echo "check-package-list: files the build read that no Debian package installed (a clean machine lacks them):"
  sed -n 's/^UNOWNED /  /p' "$tmp/result" | sort | head -n 20
  status=1
fi
if [[ -s "$tmp/unresolved" ]]; then
  echo "check-package-list: link flags not resolved: $(sort -u "$tmp/unresolved" | tr '\n' ' ')"
  status=1
fi
if (( status == 0 )); then
  echo "check-package-list: $files system files the build read all come from the $npackages listed packages or their dependencies ($(wc -l < "$tmp/covered") packages, ${ms} ms)"
else
  echo "check-package-list: FAILED ($files system files checked, ${ms} ms): add the packages above to deploy/install-deps.sh"
fi
exit "$status"
