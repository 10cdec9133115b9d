#include "shader_program.h"

#include "visq_gpu_core_embedded.h"

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

}  // namespace

std::string_view CoreShaderFiles(std::string_view name) { return core_shaders::Find(name); }

StatusOr<std::string> EmbeddedShaderText(ShaderFiles files, const std::string& file_name) {
  return Expand(files, file_name, 0);
}

StatusOr<GlProgramObject> BuildProgram(ShaderFiles files, const std::vector<ShaderSource>& sources,
                                       const ShaderDefines& defines) {
  GlProgramObject program;
  std::vector<GLuint> shaders;
  auto delete_shaders = [&] { for (GLuint s : shaders) glDeleteShader(s); };
  std::string names;
  for (const auto& source : sources) {
    absl::StrAppend(&names, names.empty() ? "" : "+", source.file_name);
    StatusOr<std::string> body = EmbeddedShaderText(files, source.file_name);
    if (!body.ok()) { delete_shaders(); return body.status(); }
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
  return program;
}

}  // namespace visq::gpu
