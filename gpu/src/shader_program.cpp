#include "shader_program.h"

#include <cctype>
#include <cstdint>
#include <cstring>

#include "visq_gpu_core_embedded.h"

#include <absl/strings/str_join.h>
#include <absl/strings/str_split.h>
#include <absl/strings/strip.h>

namespace visq::gpu {

namespace {

constexpr size_t kMaxLogChars = 4000;
constexpr int kMaxIncludeDepth = 8;

const char* StageName(GLenum stage) {
  switch (stage) {
    case GL_VERTEX_SHADER: return "vertex";
    case GL_GEOMETRY_SHADER: return "geometry";
    case GL_FRAGMENT_SHADER: return "fragment";
    case GL_COMPUTE_SHADER: return "compute";
    default: return "unknown-stage";
  }
}

std::string TrimmedLog(std::string log) {
  while (!log.empty() && (log.back() == '\n' || log.back() == ' ' || log.back() == '\0')) log.pop_back();
  if (log.size() > kMaxLogChars) log = log.substr(0, kMaxLogChars) + " [...]";
  return log;
}

StatusOr<std::string> Expand(ShaderFiles files, const std::string& file_name, int depth) {
  if (depth > kMaxIncludeDepth) return absl::InternalError(absl::StrCat(file_name, ": #include nested too deep"));
  std::string_view found = files(file_name);
  if (found.empty()) found = CoreShaderFiles(file_name);
  const absl::string_view text = AbslView(found);
  if (text.empty()) return absl::NotFoundError(absl::StrCat("shader file ", file_name, " is not embedded"));
  std::string out;
  for (absl::string_view line : absl::StrSplit(text, '\n')) {
    absl::string_view rest = absl::StripLeadingAsciiWhitespace(line);
    if (absl::ConsumePrefix(&rest, "#include")) {
      rest = absl::StripAsciiWhitespace(rest);
      if (rest.size() >= 2 && rest.front() == '"' && rest.back() == '"') {
        VISQ_ASSIGN_OR_RETURN(std::string included,
                              Expand(files, std::string(rest.substr(1, rest.size() - 2)), depth + 1));
        absl::StrAppend(&out, included, "\n");
        continue;
      }
    }
    absl::StrAppend(&out, line, "\n");
  }
  return out;
}

// Every uniform name the source declares (`uniform TYPE a, b[4];`), so that
// a name the linker dropped as unused is told from a misspelt one.
void DeclaredUniforms(std::string_view text, std::set<std::string, std::less<>>& names) {
  auto is_name_char = [](char c) { return std::isalnum(static_cast<unsigned char>(c)) || c == '_'; };
  for (size_t at = text.find("uniform"); at != std::string_view::npos; at = text.find("uniform", at + 7)) {
    if (at > 0 && is_name_char(text[at - 1])) continue;
    if (at + 7 < text.size() && is_name_char(text[at + 7])) continue;
    const size_t end = text.find_first_of(";{", at);
    if (end == std::string_view::npos || text[end] == '{') continue;  // a uniform block
    std::string_view declaration = text.substr(at + 7, end - at - 7);
    bool first = true;
    for (absl::string_view part : absl::StrSplit(AbslView(declaration), ',')) {
      if (const size_t bracket = part.find('['); bracket != absl::string_view::npos) part = part.substr(0, bracket);
      part = absl::StripAsciiWhitespace(part);
      size_t begin = part.size();
      while (begin > 0 && is_name_char(part[begin - 1])) --begin;
      if (begin < part.size() && (!first || begin > 0)) names.emplace(part.substr(begin));
      first = false;
    }
  }
}

// Active uniforms by name ("u_planes" for the array "u_planes[0]"), with
// their locations; block members (location -1) are left out.
std::map<std::string, GLint, std::less<>> ActiveUniforms(GLuint program) {
  std::map<std::string, GLint, std::less<>> out;
  GLint count = 0;
  glGetProgramInterfaceiv(program, GL_UNIFORM, GL_ACTIVE_RESOURCES, &count);
  for (GLint i = 0; i < count; ++i) {
    const GLenum properties[2] = {GL_NAME_LENGTH, GL_LOCATION};
    GLint values[2] = {0, -1};
    glGetProgramResourceiv(program, GL_UNIFORM, static_cast<GLuint>(i), 2, properties, 2, nullptr, values);
    if (values[1] < 0 || values[0] <= 0) continue;
    std::string name(static_cast<size_t>(values[0]), '\0');
    glGetProgramResourceName(program, GL_UNIFORM, static_cast<GLuint>(i), values[0], nullptr, name.data());
    name.resize(std::strlen(name.c_str()));
    if (name.ends_with("[0]")) name.resize(name.size() - 3);
    out.emplace(std::move(name), values[1]);
  }
  return out;
}

thread_local ProgramCache* current_cache = nullptr;

}  // namespace

std::string_view CoreShaderFiles(std::string_view name) { return core_shaders::Find(name); }

StatusOr<std::string> EmbeddedShaderText(ShaderFiles files, const std::string& file_name) {
  return Expand(files, file_name, 0);
}

StatusOr<std::unique_ptr<GlProgram>> BuildProgram(ShaderFiles files, const std::vector<ShaderSource>& sources,
                                                  const ShaderDefines& defines) {
  GlProgramObject program;
  std::vector<GLuint> shaders;
  auto delete_shaders = [&] { for (GLuint s : shaders) glDeleteShader(s); };
  std::string names;
  std::set<std::string, std::less<>> declared;
  for (const auto& source : sources) {
    absl::StrAppend(&names, names.empty() ? "" : "+", source.file_name);
    StatusOr<std::string> body = EmbeddedShaderText(files, source.file_name);
    if (!body.ok()) { delete_shaders(); return body.status(); }
    DeclaredUniforms(*body, declared);
    // The #version line must come first; defines follow it.
    std::string text = "#version 450 core\n";
    for (const auto& [name, value] : defines) absl::StrAppend(&text, "#define ", name, " ", value, "\n");
    absl::StrAppend(&text, "#line 1\n", *body);

    GLuint shader = glCreateShader(source.stage);
    shaders.push_back(shader);
    const char* text_ptr = text.c_str();
    glShaderSource(shader, 1, &text_ptr, nullptr);
    glCompileShader(shader);
    GLint ok = GL_FALSE;
    glGetShaderiv(shader, GL_COMPILE_STATUS, &ok);
    if (ok != GL_TRUE) {
      GLint length = 0;
      glGetShaderiv(shader, GL_INFO_LOG_LENGTH, &length);
      std::string log(std::max(length, 1), '\0');
      glGetShaderInfoLog(shader, length, nullptr, log.data());
      delete_shaders();
      return absl::InternalError(absl::StrCat("compiling ", StageName(source.stage), " shader ",
                                              source.file_name, ": ", TrimmedLog(log)));
    }
    glAttachShader(program.id(), shader);
  }
  glLinkProgram(program.id());
  delete_shaders();  // the program keeps what it needs
  GLint linked = GL_FALSE;
  glGetProgramiv(program.id(), GL_LINK_STATUS, &linked);
  if (linked != GL_TRUE) {
    GLint length = 0;
    glGetProgramiv(program.id(), GL_INFO_LOG_LENGTH, &length);
    std::string log(std::max(length, 1), '\0');
    glGetProgramInfoLog(program.id(), length, nullptr, log.data());
    return absl::InternalError(absl::StrCat("linking ", names, ": ", TrimmedLog(log)));
  }
  std::map<std::string, GLint, std::less<>> active = ActiveUniforms(program.id());
  return std::make_unique<GlProgram>(std::move(program), std::move(names), std::move(active), std::move(declared));
}

GlProgram::GlProgram(GlProgramObject object, std::string name, std::map<std::string, GLint, std::less<>> active,
                     std::set<std::string, std::less<>> declared)
    : object_(std::move(object)), name_(std::move(name)), active_(std::move(active)), declared_(std::move(declared)) {}

std::optional<GLint> GlProgram::Location(std::string_view name) const {
  if (auto it = active_.find(name); it != active_.end()) return it->second;
  if (declared_.contains(name)) return -1;
  return std::nullopt;
}

GLint UniformLocator::Locate(std::string_view name) {
  const std::optional<GLint> location = program_.Location(name);
  if (!location) undeclared_.emplace_back(name);
  return location.value_or(-1);
}

Status UniformLocator::status() const {
  if (undeclared_.empty()) return absl::OkStatus();
  return absl::InternalError(
      absl::StrCat("uniform ", absl::StrJoin(undeclared_, ", "), " declared by no shader of ", program_.name()));
}

void SetUniform(GLuint program, GLint location, int value) { glProgramUniform1i(program, location, value); }
void SetUniform(GLuint program, GLint location, unsigned value) { glProgramUniform1ui(program, location, value); }
void SetUniform(GLuint program, GLint location, float value) { glProgramUniform1f(program, location, value); }
void SetUniform(GLuint program, GLint location, bool value) { glProgramUniform1i(program, location, value ? 1 : 0); }
void SetUniform(GLuint program, GLint location, const glm::vec2& v) { glProgramUniform2f(program, location, v.x, v.y); }
void SetUniform(GLuint program, GLint location, const glm::vec3& v) {
  glProgramUniform3f(program, location, v.x, v.y, v.z);
}
void SetUniform(GLuint program, GLint location, const glm::vec4& v) {
  glProgramUniform4f(program, location, v.x, v.y, v.z, v.w);
}
void SetUniform(GLuint program, GLint location, const glm::ivec2& v) { glProgramUniform2i(program, location, v.x, v.y); }
void SetUniform(GLuint program, GLint location, const glm::ivec3& v) {
  glProgramUniform3i(program, location, v.x, v.y, v.z);
}
void SetUniform(GLuint program, GLint location, const glm::uvec2& v) {
  glProgramUniform2ui(program, location, v.x, v.y);
}
void SetUniform(GLuint program, GLint location, const glm::mat4& m) {
  glProgramUniformMatrix4fv(program, location, 1, GL_FALSE, &m[0][0]);
}
void SetUniformArray(GLuint program, GLint location, const glm::vec3* values, size_t count) {
  if (count > 0) glProgramUniform3fv(program, location, static_cast<GLsizei>(count), &values[0].x);
}
void SetUniformArray(GLuint program, GLint location, const glm::vec4* values, size_t count) {
  if (count > 0) glProgramUniform4fv(program, location, static_cast<GLsizei>(count), &values[0].x);
}
void SetUniformArray(GLuint program, GLint location, const float* values, size_t count) {
  if (count > 0) glProgramUniform1fv(program, location, static_cast<GLsizei>(count), values);
}

ProgramCache::~ProgramCache() = default;

StatusOr<const GlProgram*> ProgramCache::Get(ShaderFiles files, const std::vector<ShaderSource>& sources,
                                             const ShaderDefines& defines) {
  // The lookup function tells the algorithm libraries apart: two may embed
  // files of the same name.
  std::string key = absl::StrCat(absl::Hex(reinterpret_cast<uintptr_t>(files)), "|");
  for (const ShaderSource& s : sources) absl::StrAppend(&key, s.stage, ":", s.file_name, "+");
  for (const auto& [name, value] : defines) absl::StrAppend(&key, ";", name, "=", value);
  if (auto it = programs_.find(key); it != programs_.end()) return it->second.get();
  VISQ_ASSIGN_OR_RETURN(std::unique_ptr<GlProgram> built, BuildProgram(files, sources, defines));
  return programs_.emplace(std::move(key), std::move(built)).first->second.get();
}

void SetCurrentProgramCache(ProgramCache* cache) { current_cache = cache; }

StatusOr<const GlProgram*> CachedProgram(ShaderFiles files, const std::vector<ShaderSource>& sources,
                                         const ShaderDefines& defines) {
  if (current_cache == nullptr) return absl::InternalError("CachedProgram: not on the GL thread");
  return current_cache->Get(files, sources, defines);
}

}  // namespace visq::gpu
